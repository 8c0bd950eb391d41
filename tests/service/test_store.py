"""Durable state of the registration worker (services/store/sqlite.py, services/store/postgres.py) on real SQLite files and a
real PostgreSQL server (tests parametrised by `store_url` run on both): commits survive a reopen, a snapshot plus the
journal resume OccVO bit for bit, evicted tiles round-trip, two connections share the store; then the worker itself
(real Zenoh on loopback, in this process): a clean stop and a new worker on the same store continue a stream
exactly, with and without eviction of far map."""

from __future__ import annotations

import contextlib
import sqlite3
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import SERVICE_FRAMES as N  # frames of the `scene` fixture

from occvo_core import OccVO
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID, GridSpec
from occvo_schemas.models import SparseOccupancy
from occvo_services.array_pack import pack_arrays, unpack_arrays
from occvo_services.store.blobs import frame_digest, legacy_frame_digest, pack_frame, unpack_frame
from occvo_services.store.factory import open_store
from occvo_services.store.sqlite import TrajectoryStore
from occvo_services.store.sqlite_files import snapshot_path

warnings.filterwarnings("ignore", category=RuntimeWarning)


def _commit(store, stream, vo, frame, seq, **kw):
    r = vo.step(frame)
    store.commit_frame(
        stream,
        seq,
        frame.stamp,
        frame_digest(frame.points, frame.labels, frame.stamp),
        r.status,
        r.pose,
        pack_frame(frame),
        new_trajectory=seq == 0,
        **kw,
    )
    return r


def test_commit_survives_reopen_and_new_trajectory_drops_the_old(store_url, scene):
    store = open_store(store_url)
    poses = [np.eye(4) + i for i in range(3)]
    for i in range(3):
        f = scene[i]
        store.commit_frame(
            "car",
            i,
            f.stamp,
            frame_digest(f.points, f.labels, f.stamp),
            "ok",
            poses[i],
            pack_frame(f),
            new_trajectory=i == 0,
        )
    store.close()
    store = open_store(store_url)
    assert store.streams() == ["car"]
    rec = store.record("car")
    assert rec.last_seq == 2 and rec.snapshot_seq is None
    got = store.poses("car")
    assert [p.seq for p in got] == [0, 1, 2] and all(np.array_equal(p.pose, q) for p, q in zip(got, poses))
    assert got[1].digest == frame_digest(scene[1].points, scene[1].labels, scene[1].stamp) != got[2].digest
    journal = store.journal("car", None)
    assert [s for s, _ in journal] == [0, 1, 2]
    assert np.array_equal(journal[1][1].points, scene[1].points) and np.array_equal(
        journal[1][1].labels, scene[1].labels
    )
    assert store.pose("car", 7) is None
    # seq 0 of another trajectory replaces everything of the stream in one transaction
    f = scene[5]
    store.commit_frame("car", 0, f.stamp, b"x" * 16, "reinitialised", np.eye(4), pack_frame(f), new_trajectory=True)
    assert [p.seq for p in store.poses("car")] == [0] and store.record("car").last_seq == 0
    store.close()


def test_snapshot_and_journal_resume_bit_for_bit(store_url, scene, uninterrupted):
    store = open_store(store_url)
    vo = OccVO()
    for i in range(8):
        _commit(store, "car", vo, scene[i], i)
        if i == 4:
            packed = pack_arrays(vo.state_dict())
            assert len(packed) > (1 << 22)  # more than one chunk of the bytes path
            store.write_snapshot("car", i, vo.state_dict(copy=False))  # as the worker: streamed into the row
    store.close()
    del vo  # "crash": only the store remains

    store = open_store(store_url)
    seq, blob = store.snapshot("car")
    assert seq == 4 and store.record("car").snapshot_seq == 4 and blob == packed
    vo = OccVO()
    vo.load_state_dict(unpack_arrays(blob))
    journal = store.journal("car", seq)
    assert [s for s, _ in journal] == [5, 6, 7]  # the snapshot cleared what it covers
    stored = {p.seq: p.pose for p in store.poses("car")}
    for s, frame in journal:
        assert np.array_equal(vo.step(frame).pose, stored[s])
    for i in range(8, N):
        vo.step(scene[i])
    assert np.array_equal(vo.poses, uninterrupted)  # bit for bit, as if never stopped
    store.close()


def test_journal_frames_on_the_grid_are_kept_as_indices_exactly(scene):
    f = scene[3]
    blob = pack_frame(f)
    back = unpack_frame(blob)
    assert "ijk" in unpack_arrays(blob) and len(blob) < 0.25 * f.points.nbytes  # 3 bytes a voxel, not 24
    assert np.array_equal(back.points, f.points) and np.array_equal(back.labels, f.labels)
    assert (back.index, back.stamp) == (f.index, f.stamp)
    assert "axes" not in unpack_arrays(blob)  # voxel centres: the grid gives them
    off = OccupancyFrame(f.points + 0.01, f.labels, index=f.index, stamp=f.stamp)  # one coordinate an index: axes
    a = unpack_arrays(pack_frame(off))
    assert "axes" in a and unpack_frame(pack_frame(off)).points.tobytes() == off.points.tobytes()
    jitter = np.random.default_rng(0).uniform(-0.01, 0.01, f.points.shape)  # two coordinates an index: kept as given
    off = OccupancyFrame(f.points + jitter, f.labels, index=f.index, stamp=f.stamp)
    a = unpack_arrays(pack_frame(off))
    assert "ijk" not in a and np.array_equal(unpack_frame(pack_frame(off)).points, off.points)


def test_journal_frames_keep_the_indices_they_arrived_with(scene):
    """The lane journals a frame's indices and axes as sent, instead of deriving them again from its points."""
    f = scene[3]
    for frame in (f, OccupancyFrame(f.points + 0.01, f.labels, index=f.index, stamp=f.stamp)):
        occ = SparseOccupancy.from_points(frame.points, frame.labels, OCC3D_GRID, exact=True)
        tables = occ.index_tables(OCC3D_GRID)
        assert tables is not None
        back = unpack_frame(pack_frame(frame, tables))
        assert back.points.tobytes() == occ.to_points().tobytes() == frame.points.tobytes()
        assert np.array_equal(back.labels, frame.labels)
    other = GridSpec(lower=(-20.0, -20.0, -1.0), upper=(20.0, 20.0, 5.4))  # not the Occ3D grid: derived as before
    near = np.all(np.abs(f.points[:, :2]) < 20, axis=1)
    occ = SparseOccupancy.from_points(f.points[near], f.labels[near], other)
    assert occ.voxels is not None and occ.index_tables(OCC3D_GRID) is None


def test_a_frame_has_one_digest_whether_it_came_as_points_or_as_indices(scene):
    """The digest of a frame on the grid is taken over its compact form, as it arrived or derived from its points;
    a sender naming an index for a coordinate outside that voxel gets the digest of the points it described."""
    f = scene[3]
    for frame in (f, OccupancyFrame(f.points + 0.01, f.labels, index=f.index, stamp=f.stamp)):
        occ = SparseOccupancy.from_points(frame.points, frame.labels, OCC3D_GRID, exact=True)
        tables = occ.index_tables(OCC3D_GRID)
        assert frame_digest(occ.to_points(), frame.labels, f.stamp, tables) == frame_digest(
            frame.points, frame.labels, f.stamp
        )
    plain = frame_digest(f.points, f.labels, f.stamp)
    assert plain != frame_digest(f.points, f.labels, f.stamp + 0.5)
    moved = f.points.copy()
    moved[7, 2] += 0.4  # one voxel up: another frame
    assert plain != frame_digest(moved, f.labels, f.stamp)
    idx, axes = SparseOccupancy.from_points(f.points, f.labels, OCC3D_GRID).index_tables(OCC3D_GRID)
    axes = OCC3D_GRID.centre_table() if axes is None else axes.copy()
    axes[0, idx[0, 0]] += 0.8  # index i given the coordinate of voxel i + 2
    points = OCC3D_GRID.points_of(idx.astype(np.int64), axes)
    assert frame_digest(points, f.labels, f.stamp, (idx, axes)) == frame_digest(points, f.labels, f.stamp)


def test_cold_tiles_round_trip(store_url, scene):
    store = open_store(store_url)
    vo = OccVO()
    for i in range(3):
        _commit(store, "car", vo, scene[i], i)
    resident = vo.resident_tiles(10.0)
    blocks = vo.evict_tiles(vo.poses[-1][:2, 3], 30.0, 10.0)
    assert blocks and not (set(blocks) & vo.resident_tiles(10.0)) and set(blocks) <= resident
    _commit(store, "car", vo, scene[3], 3)
    store.finish_frame("car", 3, evicted=blocks)
    cold = store.cold_index("car")
    assert cold == {k: [3] for k in blocks}
    for (ix, iy), block in blocks.items():
        back = unpack_arrays(store.cold_block("car", ix, iy, 3))
        assert set(back) == set(block) and all(np.array_equal(back[n], block[n]) for n in block)
    # restore two of them with frame 4: gone from the cold set now, still cold as of frame 3
    two = sorted(blocks)[:2]
    vo.restore_tiles({k: unpack_arrays(store.cold_block("car", *k, 3)) for k in two})
    assert set(two) <= vo.resident_tiles(10.0)
    _commit(store, "car", vo, scene[4], 4)
    store.finish_frame("car", 4, restored=[(ix, iy, 3) for ix, iy in two])
    assert set(store.cold_index("car")) == set(blocks) - set(two)
    assert set(store.cold_index("car", as_of_seq=3)) == set(blocks)
    assert store.cold_index("car", as_of_seq=2) == {}
    # a snapshot after the restore no longer needs the restored rows
    store.write_snapshot("car", 4, pack_arrays(vo.state_dict()))
    assert store.sizes("car")["cold_tiles_rows"] == len(blocks) - 2 and store.sizes("car")["journal_rows"] == 0
    with pytest.raises(KeyError, match="no cold tile"):
        store.cold_block("car", *two[0], 3)
    store.close()


def test_two_connections_share_the_store(store_url, scene):
    a, b = open_store(store_url), open_store(store_url)
    f = scene[0]
    blob = pack_frame(f)
    assert unpack_frame(blob).index == f.index and np.array_equal(unpack_frame(blob).points, f.points)
    errors = []

    def writer(store, stream):
        try:
            for i in range(30):
                store.commit_frame(
                    stream, i, float(i), bytes(16), "ok", np.eye(4) * (i + 1), blob, new_trajectory=i == 0
                )
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(s, n)) for s, n in ((a, "one"), (b, "two"))]
    for t in threads:
        t.start()
    # a reader on a third connection sees committed rows while the writers go on (WAL)
    c = open_store(store_url)
    seen = 0
    deadline = time.monotonic() + 30
    while any(t.is_alive() for t in threads) and time.monotonic() < deadline:
        seen = max(seen, len(c.poses("one")))
    for t in threads:
        t.join(30)
    assert not errors
    assert [p.seq for p in c.poses("one")] == list(range(30)) == [p.seq for p in a.poses("two")]
    assert np.array_equal(b.pose("one", 29).pose, np.eye(4) * 30)
    if isinstance(c, TrajectoryStore):
        assert c.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    for s in (a, b, c):
        s.close()


def test_a_commit_says_whether_it_waited_for_this_store_or_for_another_process(tmp_path, scene):
    """commit_frame's phases (in a pose's timings as store_commit.lock / .begin / .commit) put a slow commit's time
    where it went: behind this store's other writers, or behind another connection holding the file (another shard)."""
    path = tmp_path / "s.sqlite"
    store, other = TrajectoryStore(path), sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    blob = pack_frame(scene[0])
    phases = store.commit_frame("car", 0, 0.0, bytes(16), "ok", np.eye(4), blob, new_trajectory=True)
    assert set(phases) == {"lock", "begin", "commit"}
    held = 0.3

    def hold(enter, leave):
        enter()
        time.sleep(held)
        leave()

    cases = {
        "lock": (store.lock.acquire, store.lock.release),
        "begin": (lambda: other.execute("BEGIN IMMEDIATE"), lambda: other.execute("COMMIT")),
    }
    for seq, (phase, (enter, leave)) in enumerate(cases.items(), start=1):
        entered = threading.Event()
        holder = threading.Thread(
            target=hold, args=(lambda enter=enter, entered=entered: (enter(), entered.set()), leave)
        )
        holder.start()
        entered.wait(5)
        phases = store.commit_frame("car", seq, float(seq), bytes(16), "ok", np.eye(4), blob)
        holder.join(5)
        waited = [k for k, ms in phases.items() if ms >= 1000 * held * 0.8]
        assert waited == [phase], phases
    other.close()
    store.close()


def test_a_niced_thread_writes_to_the_store_at_the_lanes_priority_and_goes_back(tmp_path):
    """Priority ceiling: the after-pose threads and the snapshot writer run niced, and one of them holding the store's
    write lock kept the lanes' commits waiting while other work took the cores. A writer runs at the niceness of the
    thread that opened the store while it holds the lock, then goes back, also when its lane raised it meanwhile
    (priority inheritance) and still waits for it."""
    import os

    from occvo_services.os_tuning import hold_priority, lower_priority, release_priority, set_thread_nice

    store = TrajectoryStore(tmp_path / "s.sqlite")
    lanes = os.getpriority(os.PRIO_PROCESS, 0)
    seen: dict[str, int] = {}

    def niced():
        me = threading.get_native_id()
        assert lower_priority(10)
        niced_at = os.getpriority(os.PRIO_PROCESS, me)
        if not set_thread_nice(me, lanes):
            seen["refused"] = 1
            return
        set_thread_nice(me, niced_at)
        seen["niced"] = niced_at
        store._write(lambda db: seen.__setitem__("writing", os.getpriority(os.PRIO_PROCESS, me)))
        seen["after"] = os.getpriority(os.PRIO_PROCESS, me)
        assert hold_priority(me, lanes)  # its lane waits for it
        store._write(lambda db: None)
        seen["boosted_after_write"] = os.getpriority(os.PRIO_PROCESS, me)
        release_priority(me)  # its work is over
        seen["end"] = os.getpriority(os.PRIO_PROCESS, me)

    t = threading.Thread(target=niced)
    t.start()
    t.join(10)
    store.close()
    if "refused" in seen:
        pytest.skip("raising a thread's priority needs CAP_SYS_NICE or RLIMIT_NICE here")
    assert seen == {
        "niced": lanes + 10,
        "writing": lanes,
        "after": lanes + 10,
        "boosted_after_write": lanes,
        "end": lanes + 10,
    }


def _open_at(kind: str, path: str, start: float) -> str:
    """In a pool process: open a store of `kind` on `path` at wall-clock `start` (all openers at once)."""
    from occvo_services.store.factory import open_map_store

    while time.time() < start:
        pass
    try:
        (TrajectoryStore(path) if kind == "trajectory" else open_map_store(path)).close()
        return "ok"
    except Exception as exc:  # noqa: BLE001 - reported to the test
        return f"{kind}: {exc}"


def test_shards_and_the_map_service_open_a_new_store_at_once(tmp_path):
    """Two registration shards and the map service started together open one new file: switching it to WAL needs it
    alone, and SQLite refuses that at once (no busy wait); before the retry 13 of 30 such trials failed one opener."""
    import multiprocessing as mp

    kinds = ["trajectory", "trajectory", "map", "map"]
    with mp.get_context("spawn").Pool(len(kinds)) as pool:
        pool.map(abs, range(len(kinds)))  # the processes are up before the first start time
        for trial in range(12):
            path, start = str(tmp_path / f"t{trial}" / "occvo.sqlite"), time.time() + 0.3
            results = pool.starmap(_open_at, [(k, path, start) for k in kinds], chunksize=1)
            assert results == ["ok"] * len(kinds), (trial, results)
            assert sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_a_snapshot_of_an_older_trajectory_does_not_count(store_url, scene):
    store = open_store(store_url)
    vo = OccVO()
    for i in range(3):
        _commit(store, "car", vo, scene[i], i)
    old, state = store.created("car"), vo.state_dict()
    # the stream starts again before the copy taken after seq 2 reaches the snapshot file
    again = OccVO()
    for i in range(2):
        _commit(store, "car", again, scene[5 + i], i)
    assert store.write_snapshot("car", 2, state, created=old) is False
    assert store.snapshot("car") is None and store.record("car").snapshot_seq is None
    assert [s for s, _ in store.journal("car", None)] == [0, 1]  # the new trajectory's journal is whole
    assert store.write_snapshot("car", 1, again.state_dict(copy=False)) is True
    assert store.snapshot("car")[0] == 1 and store.journal("car", None) == []
    store.close()


def test_a_store_written_before_the_snapshot_file_keeps_its_snapshot(tmp_path, scene):
    path = tmp_path / "old.sqlite"
    store = TrajectoryStore(path)
    vo = OccVO()
    for i in range(4):
        _commit(store, "car", vo, scene[i], i)
    packed = pack_arrays(vo.state_dict())
    store.close()
    for suffix in ("", "-wal", "-shm"):  # as the earlier release left it: the snapshot in the frames' file
        Path(snapshot_path(path) + suffix).unlink(missing_ok=True)
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE snapshots (stream TEXT PRIMARY KEY, seq INTEGER NOT NULL, state BLOB NOT NULL)")
    db.execute("INSERT INTO snapshots VALUES ('car', 3, ?)", (packed,))
    db.commit()
    db.close()
    store = TrajectoryStore(path)
    assert store.snapshot("car") == (3, packed)
    assert store.db.execute("SELECT 1 FROM sqlite_master WHERE name='snapshots'").fetchone() is None
    store.close()


def test_a_snapshots_file_from_before_leases_gets_its_epoch_column(tmp_path, scene):
    path = tmp_path / "s.sqlite"
    store = TrajectoryStore(path)
    vo = OccVO()
    for i in range(3):
        _commit(store, "car", vo, scene[i], i)
    packed = pack_arrays(vo.state_dict())
    store.write_snapshot("car", 2, packed)
    store.close()
    db = sqlite3.connect(snapshot_path(path))
    db.execute("ALTER TABLE snapshots DROP COLUMN epoch")  # as the release before leases wrote it
    db.commit()
    db.close()
    store = TrajectoryStore(path)
    assert store.snapshot("car") == (2, packed)
    epoch = store.acquire("car", "w1", 30.0)
    assert store.write_snapshot("car", 2, packed, epoch=epoch) and store.snapshot("car") == (2, packed)
    assert store.snap_db.execute("SELECT epoch FROM snapshots").fetchall() == [(epoch,)]
    store.close()


def test_store_refuses_an_unusable_path(tmp_path):
    from occvo_core.errors import ConfigError

    (tmp_path / "dir.sqlite").mkdir()
    with pytest.raises(ConfigError, match="trajectory store"):
        TrajectoryStore(tmp_path / "dir.sqlite")


# ------------------------------------------------------------------ the worker on its store (real Zenoh, in process)


class Pipeline:
    """Router, map service, inference worker and a registration worker that can be stopped and started again."""

    def __init__(self, store_url, **registration):
        from occvo_services.inference_worker import InferenceWorker
        from occvo_services.map_service import MapService
        from occvo_services.runtime import WorkerConfig
        from occvo_services.sessions import free_port, open_router

        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.router = open_router(self.endpoint)
        base = {"connect": self.endpoint, "log_level": "WARNING"}
        # the map service keeps its tiles in the same store (its own tables, its own connection)
        self.others = [
            MapService(WorkerConfig(**base, worker_id="map-t", store_url=str(store_url))).start(),
            InferenceWorker(WorkerConfig(**base, worker_id="inference-t")).start(),
        ]
        self.config = WorkerConfig(**base, worker_id="registration-t", store_url=str(store_url), **registration)
        self.reg = None

    def start_registration(self):
        from occvo_services.local import wait_alive
        from occvo_services.registration_worker import RegistrationWorker
        from occvo_services.sessions import open_session

        self.reg = RegistrationWorker(self.config).start()
        probe = open_session(self.endpoint)
        try:
            wait_alive(probe, ["registration", "inference", "map"], 20)
        finally:
            probe.close()
        return self.reg

    def crash_registration(self):
        """Leave like a killed process after its last commit: no shutdown snapshot."""
        self.reg.after_leaving = lambda: None
        self.reg.stop()
        self.reg.store.close()

    def close(self):
        if self.reg is not None and not self.reg.stopping.is_set():
            self.reg.stop()
        for w in self.others:
            w.stop()
        self.router.close()


def _sorted_rows(tile):
    a = np.column_stack([tile.points.to_numpy(), tile.labels.to_numpy().astype(np.float64)])
    return a[np.lexsort(a.T[::-1])]


EVICT_RADIUS_M, EVICT_TILE_M = 30.0, 10.0  # smaller than a frame's reach: tiles leave and come back within 12 frames


def _evicting_pipeline(tmp_path, path=None):
    path = path or tmp_path / "state.sqlite"
    return Pipeline(
        path, snapshot_every=3, snapshot_max_share=None, working_radius_m=EVICT_RADIUS_M, tile_m=EVICT_TILE_M
    ), path


@contextlib.contextmanager
def _ref_and_cut(svc, scene):
    """Two streams on the pipeline: `ref` driven through the scene (its poses given), `cut` reset for the test."""
    from occvo_services.client import OccVOClient

    with OccVOClient(svc.endpoint, "ref") as ref, OccVOClient(svc.endpoint, "cut") as cut:
        ref.reset()
        want = np.array([ref.step(f).matrix() for f in scene])
        cut.reset()
        yield ref, cut, want


def _same_tiles(ref, cut) -> int:
    """The map service holds the same tiles, voxel for voxel, for both streams; returns how many."""
    a = {(t.ix, t.iy): t for t in ref.region()}
    b = {(t.ix, t.iy): t for t in cut.region()}
    assert set(a) == set(b)
    for k in a:
        assert np.array_equal(_sorted_rows(a[k]), _sorted_rows(b[k])), k
    return len(a)


def _wait_map(client, seq, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if client.map_info().last_seq == seq:
                return
        except Exception:  # noqa: BLE001 - the map may not exist yet
            pass
        time.sleep(0.1)
    raise AssertionError(f"map service did not reach seq {seq}")


def test_clean_restart_continues_the_stream_and_answers_resends(store_url, scene, uninterrupted):
    from occvo_schemas.codec import encode
    from occvo_services.client import OccVOClient, camera_frame_of

    svc = Pipeline(store_url, snapshot_every=4)
    try:
        svc.start_registration()
        with OccVOClient(svc.endpoint, "car") as client:
            client.reset()
            for i in range(7):
                client.step(scene[i])
            svc.reg.stop()  # clean: a snapshot of the frames since the last one
            assert not [t.name for t in threading.enumerate() if t.name.startswith("after-car")]  # its thread ended
            probe = open_store(store_url)
            rec = probe.record("car")
            assert (rec.last_seq, rec.snapshot_seq) == (6, 6) and probe.sizes("car")["journal_rows"] == 0
            reg = svc.start_registration()
            # the new worker answers queries from the store before any frame
            traj = client.trajectory()
            assert np.array_equal(traj.poses.to_numpy(), uninterrupted[:7]) and client.pose_latest().seq == 6
            got = [client.step(scene[i]).matrix() for i in range(7, N)]
            assert np.array_equal(np.array([client.poses[i].matrix() for i in range(7)] + got), uninterrupted)
            counters = reg.stats.snapshot()[0]
            assert counters["resumes"] == 1 and counters["frames_out"] == N - 7

            # a resend of a registered frame is answered with its stored pose, not registered twice
            client.put_encoded(encode(camera_frame_of(scene[N - 1], "car", N - 1)))
            # another frame under a registered seq is refused by name
            client.put_encoded(encode(camera_frame_of(scene[2], "car", 5)))
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not (reg.stats.snapshot()[0].get("republished") and client.errors):
                time.sleep(0.05)
            counters = reg.stats.snapshot()[0]
            assert counters["republished"] == 1 and counters["frames_out"] == N - 7
            assert [(e.code, e.seq) for e in client.errors] == [("out_of_order", 5)]
            assert "differs from the registered frame" in client.errors[0].message
            assert [p.seq for p in probe.poses("car")] == list(range(N))
            assert np.array_equal(np.array([p.pose for p in probe.poses("car")]), uninterrupted)
            # seq 0 of another frame starts a new trajectory: the old one leaves the store in the same transaction
            client.reset()
            assert client.step(scene[3]).status == "initialised"
            assert [p.seq for p in probe.poses("car")] == [0] and probe.record("car").snapshot_seq is None
            probe.close()
    finally:
        svc.close()


def test_a_store_digested_before_the_compact_digest_still_knows_its_frames(tmp_path, scene, uninterrupted):
    """Frames a store took under the old digest (over the float64 points): a resend is answered, not refused."""
    from occvo_services.client import OccVOClient

    path = tmp_path / "state.sqlite"
    store, vo = TrajectoryStore(path), OccVO()
    for i in range(4):
        r = vo.step(scene[i])
        digest = legacy_frame_digest(scene[i].points, scene[i].labels, scene[i].stamp)
        status = (
            "reinitialised" if r.status == "initialised" else r.status
        )  # as the lane stored a first frame before pose v2
        store.commit_frame(
            "car", i, scene[i].stamp, digest, status, r.pose, pack_frame(scene[i]), new_trajectory=i == 0
        )
    store.close()
    svc = Pipeline(path)
    try:
        reg = svc.start_registration()
        with OccVOClient(svc.endpoint, "car") as client:
            got = [client.step(scene[i]).matrix() for i in range(N)]  # seqs 0-3 again, then the stream goes on
            assert np.array_equal(got, uninterrupted)
            # seqs 0-3 are answered from the store; a frame the client sent twice (it resends what is unanswered when
            # it first sees a worker come up, or after resend_after under load) is answered from it once more if the
            # copy came after its frame was stored
            republished = reg.stats.snapshot()[0]["republished"]
            assert 4 <= republished <= 4 + client.resends and not client.errors
    finally:
        svc.close()


def test_snapshots_keep_to_their_share_of_the_time_and_shutdown_still_writes_one(tmp_path, scene, uninterrupted):
    from occvo_services.client import OccVOClient

    path = tmp_path / "state.sqlite"
    # a share so small that even the stream's first snapshot is hours away: the journal covers the stream
    svc = Pipeline(path, snapshot_every=2, snapshot_max_share=1e-6)
    try:
        reg = svc.start_registration()
        with OccVOClient(svc.endpoint, "car") as client:
            client.reset()
            for i in range(8):
                client.step(scene[i])
            assert reg.snapshots_written(30) and "snapshots" not in reg.stats.snapshot()[0]
            probe = TrajectoryStore(path)
            assert probe.record("car").snapshot_seq is None and [s for s, _ in probe.journal("car", None)] == list(
                range(8)
            )
            svc.reg.stop()  # shutdown snapshots whatever the share
            assert probe.record("car").snapshot_seq == 7 and probe.sizes("car")["journal_rows"] == 0
            # a share of the whole time: snapshots every snapshot_every frames once the last one's time has passed
            svc.config = svc.config.model_copy(update={"snapshot_max_share": 1.0})
            reg = svc.start_registration()
            got = [client.step(scene[i]).matrix() for i in range(8, N)]
            assert np.array_equal(np.array([client.poses[i].matrix() for i in range(8)] + got), uninterrupted)
            assert reg.snapshots_written(30) and reg.stats.snapshot()[0]["snapshots"] >= 1
            assert probe.record("car").snapshot_seq > 7
            probe.close()
    finally:
        svc.close()


def test_frames_are_answered_while_the_snapshot_file_is_locked(tmp_path, scene, uninterrupted):
    from occvo_services.client import OccVOClient

    path = tmp_path / "state.sqlite"
    svc = Pipeline(path, snapshot_every=2, snapshot_max_share=None)
    blocker = None
    try:
        reg = svc.start_registration()
        blocker = sqlite3.connect(snapshot_path(path), isolation_level=None)
        blocker.execute("BEGIN IMMEDIATE")  # another writer holds the snapshot file: the first snapshot waits
        with OccVOClient(svc.endpoint, "car") as client:
            client.reset()
            # a few frames, well within the store's busy timeout: the snapshot due after seq 1 waits all along
            got = [client.step(f).matrix() for f in scene[:4]]
            assert np.array_equal(got, uninterrupted[:4])  # every frame answered, none waited for the snapshot
            assert not reg.snapshots_written(0.2) and "snapshots" not in reg.stats.snapshot()[0]
            blocker.execute("COMMIT")
            assert reg.snapshots_written(30) and reg.stats.snapshot()[0]["snapshots"] == 1  # one a stream at a time
            probe = TrajectoryStore(path)
            assert probe.record("car").snapshot_seq == 1 and [s for s, _ in probe.journal("car", 1)] == [2, 3]
            got += [client.step(f).matrix() for f in scene[4:]]
            assert np.array_equal(np.array(got), uninterrupted)
            svc.reg.stop()
            assert probe.record("car").snapshot_seq == N - 1 and probe.sizes("car")["journal_rows"] == 0
            probe.close()
    finally:
        if blocker is not None:
            blocker.close()
        svc.close()


def test_crash_with_eviction_resumes_exactly_and_the_map_service_keeps_far_tiles(tmp_path, store_url, scene):
    from occvo_core.map_tiles import tile_distance

    radius, tile_m = EVICT_RADIUS_M, EVICT_TILE_M
    svc, path = _evicting_pipeline(tmp_path, store_url)
    try:
        first = svc.start_registration()
        with _ref_and_cut(svc, scene) as (ref, cut, want):
            for i in range(8):
                cut.step(scene[i])
                # each frame's snapshot written before the next: which frames a snapshot covers is made, not timed
                assert first.snapshots_written(30)
            svc.crash_registration()
            probe = open_store(path)
            assert probe.record("cut").snapshot_seq == 5 and [s for s, _ in probe.journal("cut", 5)] == [6, 7]
            assert probe.sizes("cut")["cold_tiles_rows"] > 0
            # snapshot and cold tiles in the stored form (a third smaller), read back below as they were
            (ix, iy), seqs = next(iter(probe.cold_index("cut").items()))
            block = unpack_arrays(probe.cold_block("cut", ix, iy, seqs[0]))
            assert "counts.at" in block and "counts" not in block and block["keys"].dtype == np.int32
            assert "map.counts.at" in unpack_arrays(probe.snapshot("cut")[1])
            second = svc.start_registration()
            for i in range(8, N):
                cut.step(scene[i])
            got = np.array([cut.poses[i].matrix() for i in range(N)])
            assert np.array_equal(got, want)  # the journal replay redid the same restores and evictions
            c1, c2 = first.stats.snapshot()[0], second.stats.snapshot()[0]
            assert c1["tiles_evicted"] > 0 and c1["tiles_restored"] > 0 and c2["resumes"] == 1 and not c2["errors"]
            # the last frame's map update (and its evictions) come after its pose: the odometry is that work's until
            # its map is out (read earlier, it may still hold tiles beyond the radius)
            _wait_map(ref, N - 1)
            _wait_map(cut, N - 1)
            # the working map stays within the radius (checked when the ego changes half-tile cell)
            vo = second.sessions["cut"].vo
            resident = np.array(sorted(vo.resident_tiles(tile_m)))
            assert (tile_distance(resident, got[-1][:2, 3], tile_m) <= radius + tile_m).all()
            assert set(second.sessions["cut"].map.tiles) <= set(map(tuple, resident))
            # the map service holds resident and evicted tiles alike, equal to the uninterrupted stream's
            assert _same_tiles(ref, cut) > len(resident)
            probe.close()
    finally:
        svc.close()


def test_coalesced_map_updates_still_carry_every_evicted_tiles_last_content(tmp_path):
    """A backlog of frames (the whole drive sent at once) shares map updates, but a tile leaving the working map
    goes out with the content it had: the map service ends equal to a stream stepped frame by frame. (Frames at
    0.5 Hz, 60 m radius: a tile a frame changed can be out of the radius at the next, and not every frame evicts.)"""
    from occvo_core.sim import SyntheticScene
    from occvo_services.client import OccVOClient
    from occvo_services.commands.replay import replay

    drive = SyntheticScene(seed=5, frames=N, rate_hz=0.5)
    scene = [drive[i] for i in range(N)]
    svc = Pipeline(tmp_path / "state.sqlite", working_radius_m=60.0, tile_m=EVICT_TILE_M, map_coalesce_s=60.0)
    try:
        reg = svc.start_registration()
        with OccVOClient(svc.endpoint, "ref") as ref, OccVOClient(svc.endpoint, "cut") as cut:
            ref.reset()
            want = np.array([ref.step(f).matrix() for f in scene])
            stepped = reg.stats.snapshot()[0].get("map_updates_coalesced", 0)
            out = replay(cut, scene, window=N)
            assert np.array_equal(out["trajectory"], want) and not cut.errors
            _wait_map(ref, N - 1)
            _wait_map(cut, N - 1)
            counters = reg.stats.snapshot()[0]
            assert counters["map_updates_coalesced"] > stepped and counters["tiles_evicted"] > 0
            assert _same_tiles(ref, cut) > 0
    finally:
        svc.close()


def _disk_full_once(store, method: str, stream: str, seq: int) -> list[int]:
    """store.<method> fails once for the stream's frame `seq`, as on a full disk; returns the seqs it failed."""
    real, failed = getattr(store, method), []

    def once(s, q, *a, **kw):
        if s == stream and q == seq and not failed:
            failed.append(q)
            raise sqlite3.OperationalError("database or disk is full")
        return real(s, q, *a, **kw)

    setattr(store, method, once)
    return failed


def test_a_frame_stopped_between_its_pose_and_its_map_update_is_finished_by_the_resume(tmp_path, scene):
    """The worker commits and publishes a frame's pose before its loop-closure search and map update, then stores
    what those did (evicted tiles, restores). When that second write fails (disk full, injected once) or the worker
    dies before it, the next frame's resume replays the journal and stores it: nothing evicted is lost and the
    stream goes on exactly as the uninterrupted one."""
    svc, path = _evicting_pipeline(tmp_path)
    try:
        worker = svc.start_registration()
        with _ref_and_cut(svc, scene) as (ref, cut, want):
            _wait_map(ref, N - 1)
            probe = TrajectoryStore(path)
            evicted_at = sorted({e for seqs in probe.cold_index("ref", as_of_seq=N - 3).values() for e in seqs})
            probe.close()
            stop_at = next(e for e in evicted_at if 4 <= e < N - 2)
            failed = _disk_full_once(worker.store, "finish_frame", "cut", stop_at)
            for f in scene:
                cut.step(f)
            got = np.array([cut.poses[i].matrix() for i in range(N)])
            assert failed == [stop_at] and np.array_equal(got, want)
            errors = [e for e in cut.errors if e.code == "not_stored"]
            assert len(errors) == 1 and errors[0].seq == stop_at and "map update not stored" in errors[0].message
            c = worker.stats.snapshot()[0]
            assert c["resumes"] == 1
            _wait_map(cut, N - 1)  # the last frame's map update (and its evictions) come after its pose
            probe = TrajectoryStore(path)
            # the failed frame's evictions were stored by the resume: the same cold tiles, evicted at the same frames
            assert probe.cold_index("cut") == probe.cold_index("ref") and stop_at in {
                e for seqs in probe.cold_index("cut", as_of_seq=stop_at).values() for e in seqs
            }
            _same_tiles(ref, cut)
            probe.close()
    finally:
        svc.close()


def test_a_caught_up_frame_whose_commit_fails_publishes_no_pose_and_is_resent(tmp_path, scene):
    """Caught up, a frame's registration, commit and pose publication are one call in the kernel team's thread. When
    its commit fails (disk full, injected once) no pose goes out, the client hears why (`not_stored`, not an answer)
    and sends the frame again; the stream resumes from the store: every pose is there, an offline run's."""
    from occvo_services.client import OccVOClient

    fail_at = N // 2
    svc = Pipeline(tmp_path / "state.sqlite", kernel_threads=2)  # two kernel threads: the team's thread does it all
    try:
        worker = svc.start_registration()
        failed = _disk_full_once(worker.store, "commit_frame", "car", fail_at)
        with OccVOClient(svc.endpoint, "car", resend_after=0.5) as client:
            client.reset()
            got = [client.step(f).matrix() for f in scene]
            refused = [e for e in client.errors if e.code == "not_stored"]
        assert [e.seq for e in refused] == [fail_at] and "disk is full" in refused[0].message
        vo = OccVO()
        want = [vo.step(f).pose for f in scene]
        assert failed == [fail_at] and np.array_equal(np.array(got), np.array(want))
        assert worker.stats.snapshot()[0]["resumes"] == 1
        stored = TrajectoryStore(tmp_path / "state.sqlite")
        assert [p.seq for p in stored.poses("car")] == list(range(N))
        stored.close()
    finally:
        svc.close()


def test_a_failed_frame_resent_before_its_error_arrives_is_registered_once_and_its_pose_is_stored(tmp_path, scene):
    """The interleaving a busy machine makes: the client, answered nothing for resend_after, sends a frame again while
    the worker still works on it, and the first copy's commit fails. The failed copy publishes no pose; the resent copy
    is a new attempt: registered (after the stream resumes from the store), committed, then published. So the pose the
    client holds for that seq is the stored one, and the stream is an offline run's over every frame."""
    from occvo_services.client import OccVOClient

    fail_at = N // 2
    svc = Pipeline(tmp_path / "state.sqlite", kernel_threads=1)
    try:
        worker = svc.start_registration()
        real, failed = worker.store.commit_frame, []
        resent = threading.Event()

        def fails_once_resent(s, q, *a, **kw):
            if s == "car" and q == fail_at and not failed:
                failed.append(q)
                # the commit fails only once the client's resend reached the worker (made, not hoped for)
                resent.wait(60)
                raise sqlite3.OperationalError("database or disk is full")
            return real(s, q, *a, **kw)

        worker.store.commit_frame = fails_once_resent
        with OccVOClient(svc.endpoint, "car", resend_after=0.2) as client:
            client.reset()
            got = [client.step(f).matrix() for f in scene[:fail_at]]
            frames_in = worker.stats.snapshot()[0]["frames_in"]
            client.publish(scene[fail_at])
            deadline = time.monotonic() + 60
            while worker.stats.snapshot()[0]["frames_in"] < frames_in + 2 and time.monotonic() < deadline:
                time.sleep(0.01)  # the original and its resend both reached the worker
            resent.set()
            with client._cv:  # both answers: the failed copy's error and the resend's pose
                assert client._cv.wait_for(
                    lambda: fail_at in client.poses and any(e.seq == fail_at for e in client.errors), 60
                )
            (error,) = [e for e in client.errors if e.seq == fail_at]
            assert error.code == "not_stored" and f"seq {fail_at} not stored, pose not published" in error.message
            pose = client.poses[fail_at]
            got.append(pose.matrix())
            got += [client.step(f).matrix() for f in scene[fail_at + 1 :]]
            assert client.resends >= 1
        vo = OccVO()
        want = [vo.step(f).pose for f in scene]
        assert failed == [fail_at] and np.array_equal(np.array(got), np.array(want))
        stored = TrajectoryStore(tmp_path / "state.sqlite")
        assert [p.seq for p in stored.poses("car")] == list(range(N))
        assert np.array_equal(stored.pose("car", fail_at).pose, pose.matrix())
        stored.close()
    finally:
        svc.close()


def test_a_closed_loop_publishes_the_odometry_pose_then_the_relocalised_one(tmp_path):
    """A frame that closes a loop is answered at once with its odometry pose; the search and the correction run
    after it, and the relocalised pose follows (status "relocalised"), replacing it in the client, the store and
    the trajectory query. Drift is injected as in test_loop_closure (what a long drive does)."""
    import sys

    from occvo_core.sim import SyntheticScene
    from occvo_schemas import keys
    from occvo_schemas.codec import decode
    from occvo_schemas.models import PoseEstimate
    from occvo_services.client import OccVOClient

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))  # test_loop_closure's drive
    from test_loop_closure import EVICT_AT, FRAMES, _config, _drift, _drive, inject_drift

    loop = SyntheticScene(seed=1, frames=FRAMES, route="loop", loop_blocks=(1, 1))
    cfg, drift = _config(True), _drift(2.0, [6.0, -4.0, 0.0])
    offline, closures, _, _ = _drive(loop, cfg, drift)
    (tmp_path / "occvo.json").write_text(cfg.model_dump_json())
    svc = Pipeline(tmp_path / "state.sqlite", snapshot_every=10**6, occvo_config=str(tmp_path / "occvo.json"))
    heard: list[tuple[int, str]] = []
    try:
        worker = svc.start_registration()
        with OccVOClient(svc.endpoint, "lap") as client:
            sub = client.session.declare_subscriber(
                keys.pose("lap"),
                lambda s: heard.append((lambda p: (p.seq, p.status))(decode(s.payload.to_bytes(), PoseEstimate))),
            )
            client.reset()
            cold = {}
            start = loop.gt_poses[0, :2, 3]
            for i in range(FRAMES):
                vo = worker.sessions["lap"].vo if i else None
                if cold and np.linalg.norm(loop.gt_poses[i, :2, 3] - start) < 40.0:
                    vo.restore_tiles(cold)  # between frames: the lane has finished the last one (its map is out)
                    cold = {}
                client.step(loop[i])
                _wait_map(client, i)
                if i == EVICT_AT:
                    cold = inject_drift(worker.sessions["lap"].vo, drift)
            deadline = time.monotonic() + 10
            while len(heard) < FRAMES + len(closures) and time.monotonic() < deadline:
                time.sleep(0.05)
            sub.undeclare()
            got = np.array([client.poses[i].matrix() for i in range(FRAMES)])
            trajectory = client.trajectory()
        assert closures and [s for s, st in heard if st == "relocalised"] == [t for t, _ in closures]
        for t, _correction in closures:
            at = heard.index((t, "relocalised"))
            assert heard[at - 1] == (t, "ok") and all(
                s < t for s, _ in heard[: at - 1]
            )  # pose first, then the correction
            assert client.poses[t].status == "relocalised"
        same = [i for i in range(FRAMES) if i not in (EVICT_AT - 1, EVICT_AT)]  # their poses moved after publishing
        assert np.array_equal(got[same], offline.poses[same])
        assert np.array_equal(trajectory.poses.to_numpy(), got)
        stored = {p.seq: p for p in TrajectoryStore(tmp_path / "state.sqlite").poses("lap")}
        assert all(np.array_equal(stored[i].pose, got[i]) for i in range(FRAMES))
        assert [s for s, p in stored.items() if p.status == "relocalised"] == [t for t, _ in closures]
    finally:
        svc.close()


def test_frame_commits_leave_the_wal_checkpoint_to_the_stores_own_thread(tmp_path, monkeypatch):
    """A commit only appends to the WAL (its copy into the file held every stream's commit behind the store's lock);
    the checkpointer thread copies it, and the rows read back after a reopen."""

    def commit_all(store, n=12):
        for i in range(n):  # 1 MB journal entries: past SQLite's 4 MB autocheckpoint threshold
            store.commit_frame(
                "car", i, float(i), b"d" * 16, "ok", np.eye(4) * i, bytes([i]) * 2**20, new_trajectory=i == 0
            )

    db = lambda p: Path(p).stat().st_size / 2**20  # noqa: E731
    monkeypatch.setattr(TrajectoryStore, "CHECKPOINT_EVERY_S", 3600.0)  # no pass during this part
    store = TrajectoryStore(tmp_path / "a.sqlite")
    commit_all(store)
    assert db(tmp_path / "a.sqlite") < 1 and db(tmp_path / "a.sqlite-wal") > 12  # nothing copied by the commits
    store.close()

    monkeypatch.setattr(TrajectoryStore, "CHECKPOINT_EVERY_S", 0.05)
    store = TrajectoryStore(tmp_path / "b.sqlite")
    commit_all(store)
    deadline = time.monotonic() + 30
    while db(tmp_path / "b.sqlite") < 12 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert db(tmp_path / "b.sqlite") >= 12  # the checkpointer copied the WAL into the file
    store.close()
    store = TrajectoryStore(tmp_path / "b.sqlite")
    assert [p.seq for p in store.poses("car")] == list(range(12)) and store.poses("car")[5].pose[0, 0] == 5
    assert [s for s, _ in store._read("SELECT seq, frame FROM journal WHERE stream='car'")] == list(range(12))
    # a new snapshots' file has 64 kB pages (a third of 4 kB pages' CPU per snapshot)
    assert store.snap_db.execute("PRAGMA page_size").fetchone()[0] == 65536
    store.close()


def test_the_database_down_refuses_frames_by_name_and_the_stream_goes_on_when_it_is_back(pg_cluster, pg_url, scene):
    """PostgreSQL stopped mid-drive: the frame in hand is refused with one line naming the store
    (`store_unavailable`, its pose not published); once the server is back the client's resend is registered and the stream goes on: every
    pose is there and stored, an offline run's."""
    from occvo_services.client import OccVOClient

    fail_at = N // 2
    svc = Pipeline(pg_url, kernel_threads=2)
    try:
        worker = svc.start_registration()
        with OccVOClient(svc.endpoint, "car", resend_after=1.0) as client:
            client.reset()
            got = [client.step(f).matrix() for f in scene[:fail_at]]
            pg_cluster.stop()
            try:
                client.publish(scene[fail_at])
                with client._cv:
                    assert client._cv.wait_for(lambda: any(e.seq == fail_at for e in client.errors), 60)
            finally:
                pg_cluster.start()
            got.append(client.wait_pose(fail_at, timeout=120).matrix())
            got += [client.step(f).matrix() for f in scene[fail_at + 1 :]]
            [error] = [e for e in client.errors if e.seq == fail_at][:1]
        assert error.code == "store_unavailable" and "store postgresql://" in error.message
        assert "unreachable" in error.message
        vo = OccVO()
        want = [vo.step(f).pose for f in scene]
        assert np.array_equal(np.array(got), np.array(want)) and worker.stats.snapshot()[0]["resumes"] >= 1
        stored = open_store(pg_url)
        assert [p.seq for p in stored.poses("car")] == list(range(N))
        stored.close()
    finally:
        svc.close()
