"""The map service's durable store: SQLite tables map_streams/map_tiles (unit tests on real files, two processes on
one file), and a map service process killed with SIGKILL and restarted on the same file serving the same bytes."""

from __future__ import annotations

import multiprocessing
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from occvo_core.errors import ConfigError
from occvo_core.map_tiles import tiles_from_map
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import Array, MapInfo, MapTile, MapUpdate
from occvo_services.local import wait_alive
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import free_port, open_router, open_session
from occvo_services.store.factory import open_map_store
from occvo_services.store.map_tiles import MapStore, MemoryMapStore

REPO = Path(__file__).resolve().parents[2]


def tile(stream, ix, iy, seq, points, labels=None, tile_m=20.0):
    points = np.asarray(points, np.float64).reshape(-1, 3)
    labels = np.zeros(len(points), np.uint8) if labels is None else np.asarray(labels, np.uint8)
    return MapTile(
        stream=stream,
        ix=ix,
        iy=iy,
        tile_m=tile_m,
        seq=seq,
        points=Array.from_numpy(points),
        labels=Array.from_numpy(labels),
    )


def random_tiles(rng, stream, seq, n=3000, lo=-50, hi=50, tile_m=20.0):
    pts = rng.uniform(lo, hi, (n, 3))
    pts[:, 2] = rng.uniform(-1, 5, n)
    return [
        tile(stream, ix, iy, seq, p, l, tile_m)
        for (ix, iy), (p, l) in sorted(tiles_from_map(pts, rng.integers(0, 17, n).astype(np.uint8), tile_m).items())
    ]


def apply(store, update: MapUpdate) -> None:
    store.apply(update, [encode(t, 1 << 30) for t in update.tiles])


def expected_info(stream, tiles: dict, tile_m, last_seq) -> MapInfo:
    pts = [t.points.to_numpy() for t in tiles.values()]
    return MapInfo(
        stream=stream,
        tile_m=tile_m,
        tile_count=len(tiles),
        voxel_count=sum(len(p) for p in pts),
        last_seq=last_seq,
        bounds_min=tuple(np.concatenate(pts).min(0).tolist()) if pts else None,
        bounds_max=tuple(np.concatenate(pts).max(0).tolist()) if pts else None,
        tiles=sorted(tiles),
    )


def contents(store, stream):
    return {(ix, iy): data for ix, iy, data in store.tiles(stream)}


@pytest.fixture(params=["sqlite", "memory", "postgresql"])
def store(request, tmp_path):
    if request.param == "postgresql":
        s = open_map_store(request.getfixturevalue("pg_url"))
    else:
        s = MapStore(tmp_path / "map.sqlite") if request.param == "sqlite" else MemoryMapStore()
    yield s
    s.close()


# ------------------------------------------------------------------ the store


def test_updates_resets_and_empty_tiles(store):
    rng = np.random.default_rng(0)
    first = random_tiles(rng, "car", 0)
    apply(store, MapUpdate(stream="car", seq=0, reset=True, tile_m=20.0, tiles=first))
    apply(
        store,
        MapUpdate(stream="other", seq=0, reset=True, tile_m=10.0, tiles=random_tiles(rng, "other", 0, tile_m=10.0)),
    )
    have = {(t.ix, t.iy): t for t in first}
    assert contents(store, "car") == {k: encode(t, 1 << 30) for k, t in have.items()}
    assert store.info("car") == expected_info("car", have, 20.0, 0)

    # seq 1 changes one tile, empties another and says nothing of the rest: the rest stays (evicted, not emptied)
    keys_ = sorted(have)
    changed = tile("car", *keys_[0], 1, [[keys_[0][0] * 20 + 1.0, keys_[0][1] * 20 + 1.0, 0.2]], [5])
    emptied = tile("car", *keys_[1], 1, np.zeros((0, 3)))
    apply(store, MapUpdate(stream="car", seq=1, tile_m=20.0, tiles=[changed, emptied]))
    have[keys_[0]] = changed
    del have[keys_[1]]
    got = contents(store, "car")
    assert set(got) == set(have) and decode(got[keys_[0]], MapTile) == changed
    assert store.info("car") == expected_info("car", have, 20.0, 1)
    assert store.tiles("car", *keys_[1]) == [] and store.tiles("car", 999, 999) == []
    assert [t[:2] for t in store.tiles("car", *keys_[2])] == [keys_[2]]

    # a region query bounded by indices
    from occvo_schemas.models import MapTileQuery

    b = MapTileQuery(stream="car", ix_min=0, iy_max=0)
    assert [t[:2] for t in store.tiles("car", bounds=b)] == sorted(k for k in have if k[0] >= 0 and k[1] <= 0)

    # a reset drops every tile of that stream, and only of that stream
    other_before = contents(store, "other")
    fresh = random_tiles(rng, "car", 0, lo=100, hi=130)
    apply(store, MapUpdate(stream="car", seq=0, reset=True, tile_m=20.0, tiles=fresh))
    assert set(contents(store, "car")) == {(t.ix, t.iy) for t in fresh}
    assert store.info("car") == expected_info("car", {(t.ix, t.iy): t for t in fresh}, 20.0, 0)
    assert contents(store, "other") == other_before and store.info("other").tile_m == 10.0
    assert store.streams() == ["car", "other"]
    # a reset with no tiles leaves an empty map, still known
    apply(store, MapUpdate(stream="car", seq=0, reset=True, tile_m=20.0))
    info = store.info("car")
    assert info.tile_count == 0 and info.voxel_count == 0 and info.bounds_min is None and info.last_seq == 0
    assert store.info("nobody") is None and store.tiles("nobody") == []


def test_sqlite_and_postgresql_agree_with_memory(tmp_path, pg_url):
    rng = np.random.default_rng(3)
    a, b, c = MapStore(tmp_path / "m.sqlite"), MemoryMapStore(), open_map_store(pg_url)
    for seq in range(6):
        u = MapUpdate(
            stream="s",
            seq=seq,
            reset=seq == 0,
            tile_m=20.0,
            tiles=random_tiles(rng, "s", seq, n=500 * (seq + 1))[: 2 + seq % 3]
            + [tile("s", 9, 9, seq, np.zeros((0, 3)))],
        )
        for s in (a, b, c):
            apply(s, u)
        assert a.info("s") == b.info("s") == c.info("s") and contents(a, "s") == contents(b, "s") == contents(c, "s")
    a.close()
    c.close()


def test_reopen_gives_the_same_tiles(tmp_path):
    path = tmp_path / "deep" / "map.sqlite"  # the folder is made
    rng = np.random.default_rng(1)
    s = MapStore(path)
    for seq in range(4):
        apply(
            s,
            MapUpdate(
                stream="car",
                seq=seq,
                reset=seq == 0,
                tile_m=20.0,
                tiles=random_tiles(rng, "car", seq, n=400 + 100 * seq),
            ),
        )
    before, info = contents(s, "car"), s.info("car")
    s.close()
    s2 = open_map_store(path)
    assert isinstance(s2, MapStore) and contents(s2, "car") == before and s2.info("car") == info and info.last_seq == 3
    c = sqlite3.connect(path)
    assert c.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert {r[0] for r in c.execute("SELECT name FROM sqlite_master WHERE type = 'table'")} >= {
        "map_tiles",
        "map_streams",
    }
    c.close()
    s2.close()


def test_unusable_path_is_a_config_error(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="map store"):
        open_map_store(tmp_path / "file" / "map.sqlite")
    (tmp_path / "junk.sqlite").write_bytes(b"not a database at all" * 100)
    with pytest.raises(ConfigError, match="junk.sqlite"):
        open_map_store(tmp_path / "junk.sqlite")
    assert isinstance(open_map_store(None), MemoryMapStore)


def _writer(path: str, stream: str, n: int, other_table: bool) -> None:
    """One process writing its stream's updates; optionally also another table through its own connection, as the
    registration worker's store does in the same file."""
    rng = np.random.default_rng(len(stream))
    s = MapStore(path)
    c = None
    if other_table:
        c = sqlite3.connect(path, timeout=30, isolation_level=None)
        c.execute("PRAGMA busy_timeout = 30000")
        c.execute("CREATE TABLE IF NOT EXISTS other_state (k INTEGER PRIMARY KEY, v BLOB)")
    for seq in range(n):
        apply(
            s,
            MapUpdate(stream=stream, seq=seq, reset=seq == 0, tile_m=20.0, tiles=random_tiles(rng, stream, seq, n=300)),
        )
        if c is not None:
            c.execute("BEGIN IMMEDIATE")
            c.execute("INSERT OR REPLACE INTO other_state VALUES (?, ?)", (seq, os.urandom(20000)))
            c.execute("COMMIT")
    s.close()


def test_two_processes_write_one_file(tmp_path):
    path = str(tmp_path / "shared.sqlite")
    ctx = multiprocessing.get_context("spawn")
    procs = [
        ctx.Process(target=_writer, args=(path, "a", 40, False)),
        ctx.Process(target=_writer, args=(path, "b", 40, True)),
    ]
    for p in procs:
        p.start()
    reader = MapStore(path)
    seen = 0
    while any(p.is_alive() for p in procs):  # reads go on while both write
        for st in reader.streams():
            info = reader.info(st)
            assert info.tile_count == len(reader.tiles(st)) or info.last_seq is not None
            seen += 1
        time.sleep(0.01)
    for p in procs:
        p.join(30)
        assert p.exitcode == 0
    assert reader.streams() == ["a", "b"] and seen > 0
    for st in "ab":  # each stream holds exactly the tiles of its last update
        rng = np.random.default_rng(len(st))
        for seq in range(40):
            last = random_tiles(rng, st, seq, n=300)
        assert reader.info(st).last_seq == 39 and contents(reader, st) == {
            (t.ix, t.iy): encode(t, 1 << 30) for t in last
        }
    c = sqlite3.connect(path)
    assert c.execute("SELECT COUNT(*) FROM other_state").fetchone()[0] == 40
    c.close()
    reader.close()


# ------------------------------------------------------------------ the service, killed and restarted


def start_map_service(ep: str, store: Path | str, wid: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "occvo_services.map_service",
            "--connect",
            ep,
            "--store-url",
            str(store),
            "--worker-id",
            wid,
            "--log-level",
            "WARNING",
        ],
        cwd=REPO,
        env=env,
    )


def region(session, stream) -> dict[str, bytes]:
    out = {}
    for r in session.get(keys.map_tile(stream, "*", "*"), timeout=10.0):
        assert r.ok is not None, r.err.payload.to_bytes()
        out[str(r.ok.key_expr)] = r.ok.payload.to_bytes()
    return out


def info_of(session, stream) -> MapInfo | None:
    for r in session.get(keys.map_info(stream), timeout=10.0):
        if r.ok is not None:
            return decode(r.ok.payload.to_bytes(), MapInfo)
    return None


def wait_seq(session, stream, seq, timeout=20.0) -> MapInfo:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = info_of(session, stream)
        if info is not None and info.last_seq == seq:
            return info
        time.sleep(0.05)
    raise AssertionError(f"map service did not reach seq {seq} of {stream}")


def test_map_service_killed_and_restarted_serves_the_same_tiles(store_url):
    ep = f"tcp/127.0.0.1:{free_port()}"
    store = store_url
    router = open_router(ep)
    session = open_session(ep)
    procs = []
    try:
        procs.append(start_map_service(ep, store, "map-a"))
        wait_alive(session, ["map"], 30)
        pub = session.declare_publisher(keys.map_updates("car"), congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)
        rng = np.random.default_rng(7)
        first = random_tiles(rng, "car", 0, n=5000, lo=-60, hi=60)
        pub.put(encode(MapUpdate(stream="car", seq=0, reset=True, tile_m=20.0, tiles=first), 1 << 30))
        # seq 1..3 touch a few tiles each and empty one; the others are never sent again and must stay
        for seq in range(1, 4):
            ups = random_tiles(rng, "car", seq, n=800, lo=0, hi=39)
            ups.append(tile("car", -3, -3, seq, np.zeros((0, 3))))
            pub.put(encode(MapUpdate(stream="car", seq=seq, tile_m=20.0, tiles=ups), 1 << 30))
        info = wait_seq(session, "car", 3)
        tiles = region(session, "car")
        assert (-3, -3) not in info.tiles and len(tiles) == info.tile_count == len(first) - 1
        assert keys.map_tile("car", -2, -2) in tiles  # sent once at seq 0, never again
        one = next(iter(session.get(keys.map_tile("car", 0, 0), timeout=10.0))).ok.payload.to_bytes()

        procs[0].kill()  # SIGKILL: no shutdown path runs
        assert procs[0].wait(10) == -9
        deadline = time.monotonic() + 20
        while info_of(session, "car") is not None and time.monotonic() < deadline:
            time.sleep(0.1)  # nobody serves the map now
        procs.append(start_map_service(ep, store, "map-b"))
        wait_alive(session, ["map"], 30)
        assert info_of(session, "car") == info
        assert region(session, "car") == tiles
        assert next(iter(session.get(keys.map_tile("car", 0, 0), timeout=10.0))).ok.payload.to_bytes() == one

        # and it goes on from there: a new update lands on top of the restored tiles
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)
        extra = tile("car", 30, 30, 4, [[601.0, 601.0, 1.0]], [3])
        pub.put(encode(MapUpdate(stream="car", seq=4, tile_m=20.0, tiles=[extra]), 1 << 30))
        after = wait_seq(session, "car", 4)
        assert after.tile_count == info.tile_count + 1 and after.voxel_count == info.voxel_count + 1
        assert decode(region(session, "car")[keys.map_tile("car", 30, 30)], MapTile) == extra
        pub.undeclare()
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        session.close()
        router.close()


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_pipeline_in_threads_map_survives_a_map_service_restart(tmp_path, backend, request):
    """Router and the three workers as threads, map service on a store: a replayed synthetic scene's tiles equal
    the offline map, and a new map service on the same file serves them unchanged."""
    from occvo_core import OccVO
    from occvo_core.sim import SyntheticScene
    from occvo_services.client import OccVOClient
    from occvo_services.commands.replay import replay
    from occvo_services.inference_worker import InferenceWorker
    from occvo_services.map_service import MapService
    from occvo_services.registration_worker import RegistrationWorker

    ep = f"tcp/127.0.0.1:{free_port()}"
    store = tmp_path / "occvo.sqlite" if backend == "sqlite" else request.getfixturevalue("pg_url")
    router = open_router(ep)
    cfg = {"connect": ep, "log_level": "WARNING"}
    workers = [
        MapService(WorkerConfig(**cfg, worker_id="map-1", store_path=str(store))).start(),
        RegistrationWorker(WorkerConfig(**cfg, worker_id="registration-1")).start(),
        InferenceWorker(WorkerConfig(**cfg, worker_id="inference-1")).start(),
    ]
    try:
        scene = SyntheticScene(seed=2, frames=3)
        with OccVOClient(ep, "sim") as c:
            c.wait_for_workers()
            out = replay(c, scene, window=2)
            assert out["poses"] == 3 and not c.errors
            info = wait_seq(c.session, "sim", 2)
            tiles = region(c.session, "sim")
            vo = OccVO()
            vo.reset()
            for i in range(3):
                vo.step(scene[i])
            offline = tiles_from_map(*vo.map_points(), 20.0)
            assert set(info.tiles) == set(offline)
            for (ix, iy), (p, l) in offline.items():
                t = decode(tiles[keys.map_tile("sim", ix, iy)], MapTile)
                assert np.array_equal(t.points.to_numpy(), p) and np.array_equal(t.labels.to_numpy(), l)

            workers[0].stop()
            workers[0] = MapService(WorkerConfig(**cfg, worker_id="map-2", store_path=str(store))).start()
            wait_alive(c.session, ["map"], 30)
            assert info_of(c.session, "sim") == info and region(c.session, "sim") == tiles
    finally:
        for w in reversed(workers):
            w.stop()
        router.close()
