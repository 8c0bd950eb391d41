"""The store's capacity on PostgreSQL: what a frame costs the store, and where one primary saturates.

    python benchmarks/store_capacity.py [--placements members,shards] [--rate 2] [--clients 1,2,4,8,16,32]
                                        [--seconds 15] [--python-clients 1,2,4] [--repeats 3] [--skip-drive]
                                        [--output F.json]

A throwaway PostgreSQL 15 cluster is started as the tests start it (occvo_services.store.pg_local: fsync on, the
defaults otherwise). Three measures, one after the other on it:

- per_frame: the real service (router + the three workers, LocalService) with the registration worker and the map
  service on the cluster, under each --placements ("members" as a fleet of hosts runs, "shards"); each real scene a
  car driving at --rate frames a second, all at once (lossless replay, window 4). The write-ahead log's bytes
  (pg_current_wal_lsn), the write transactions (the next transaction id: a read takes none), the WAL flushes
  (pg_stat_wal.wal_sync), the database's growth and the snapshots written over the drives, over the frames; and what
  the store holds after them per table; and what a pose row takes on disk (50,000 of them, with their index).
- server: pgbench clients (C, so the server is what saturates) each running a frame's synchronous commit a
  transaction, the statements of commit_frame (services/store/frame_log.py): the lease row FOR SHARE, the stream's
  row, the pose, a journal entry of the drives' median frame size, the usage update; --seconds at each count in
  --clients, the sweep repeated --repeats times (medians). commits/s and WAL MB/s; where more clients stop adding
  commits is where the primary saturates.
- python: the same commits through the store's own code (processes calling commit_frame on their own stream), so
  that the client's share of the cost shows beside the server's.

On a shared host the figures are this host's: compare them within one run. Prints JSON (docs/capacity.md)."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from occvo_services.store.pg_local import BIN, PgCluster, missing

DATA = Path(__file__).resolve().parents[2] / "shared/data/occvo-sample/occupancy"
SCENES = ("scene-0101", "scene-0268")


def counters(url: str) -> dict[str, float]:
    """The cluster's WAL position (bytes), next transaction id, WAL flushes, the database's size, and the rows each
    table took in (inserted or updated: a snapshot's COPY is one insert)."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("SELECT pg_stat_force_next_flush()")
        row = conn.execute(
            "SELECT pg_wal_lsn_diff(pg_current_wal_lsn(), '0/0'), pg_snapshot_xmax(pg_current_snapshot())::text::bigint,"
            " (SELECT wal_sync FROM pg_stat_wal), pg_database_size(current_database())"
        ).fetchone()
        tables = conn.execute("SELECT relname, n_tup_ins + n_tup_upd FROM pg_stat_user_tables").fetchall()
    out = {"wal_bytes": float(row[0]), "xid": float(row[1]), "wal_sync": float(row[2]), "db_bytes": float(row[3])}
    return out | {f"rows_{name}": float(n) for name, n in tables}


def frames_of(name: str) -> list:
    from occvo_core.datasets import open_scene

    scene = open_scene(DATA / name)
    return [scene[i] for i in range(len(scene))]


def per_frame(url: str, placement: str, rate_hz: float) -> dict:
    """The real service on the cluster, each real scene a car driving at rate_hz at once: the store's cost of a
    frame, over every frame of the drives."""
    from occvo_services.local import LocalService

    drives = {name.replace("scene-", "real"): frames_of(name) for name in SCENES if (DATA / name).is_dir()}
    store = ["--store-url", url]
    args = {"registration": store, "map": store}
    with LocalService(quiet=True, worker_args=args, placement=placement) as svc:
        time.sleep(3.0)  # the workers' start-up writes (schema, first lease renewals) settle
        before, t0 = counters(url), time.perf_counter()
        drive_all(svc.endpoint, drives, rate_hz)
        time.sleep(3.0)  # the work after the last poses (map tiles, snapshots) lands
        after, wall = counters(url), time.perf_counter() - t0
    n = sum(len(f) for f in drives.values())
    d = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in after}
    stored = stored_bytes(url)
    return {
        "placement": placement,
        "rate_hz": rate_hz,
        "frames": n,
        "drive_s": round(wall, 1),
        "wal_kb_per_frame": round(d["wal_bytes"] / n / 1e3, 1),
        "write_transactions_per_frame": round(d["xid"] / n, 2),
        "wal_flushes_per_frame": round(d["wal_sync"] / n, 2),
        "db_growth_kb_per_frame": round(d["db_bytes"] / n / 1e3, 1),
        "snapshots_written": int(d.get("rows_snapshots", 0)),
        "snapshot_mb_mean": round(stored["snapshot_bytes"] / max(stored["snapshots"], 1) / 1e6, 1),
        "map_tile_writes_per_frame": round(d.get("rows_map_tiles", 0) / n, 1),
        "stored_kb_per_frame": {k: round(v / n / 1e3, 2) for k, v in stored.items() if k.endswith("_bytes")},
    }


def drive_all(endpoint: str, drives: dict, rate_hz: float) -> None:
    """Every drive at once, a client each (lossless replay, window 4)."""
    import threading

    from occvo_services.client import OccVOClient
    from occvo_services.commands.replay import replay

    def one(stream: str, frames: list) -> None:
        with OccVOClient(endpoint, stream, timeout=120, resend_after=5.0) as c:
            replay(c, frames, rate_hz=rate_hz, window=4, timeout=120)

    threads = [threading.Thread(target=one, args=item) for item in drives.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def stored_bytes(url: str) -> dict[str, int]:
    """What the store holds after the drives: rows' bytes per table (the map service's tiles included)."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        q = lambda sql: conn.execute(sql).fetchone()  # noqa: E731
        poses, journal = q("SELECT SUM(LENGTH(pose)) FROM poses")[0], q("SELECT SUM(LENGTH(frame)) FROM journal")[0]
        snaps, snap_bytes = q("SELECT COUNT(*), SUM(LENGTH(state)) FROM snapshots")
        cold, tiles = q("SELECT SUM(LENGTH(block)) FROM cold_tiles")[0], q("SELECT SUM(LENGTH(data)) FROM map_tiles")[0]
    return {
        "poses_bytes": int(poses or 0),
        "journal_bytes": int(journal or 0),
        "snapshots": int(snaps),
        "snapshot_bytes": int(snap_bytes or 0),
        "cold_tiles_bytes": int(cold or 0),
        "map_tiles_bytes": int(tiles or 0),
    }


FRAME_SQL = """\\set seq random(1, 1000000000)
BEGIN;
SELECT epoch, owner FROM leases WHERE stream = 'car' || :client_id FOR SHARE;
INSERT INTO streams (stream, created, last_seq) VALUES ('car' || :client_id, 0, :seq) ON CONFLICT (stream) DO UPDATE SET last_seq = excluded.last_seq;
INSERT INTO poses SELECT 'car' || :client_id, :seq, 0.0, digest, 'ok', pose FROM bench_frame ON CONFLICT (stream, seq) DO UPDATE SET stamp = excluded.stamp, digest = excluded.digest, status = excluded.status, pose = excluded.pose;
INSERT INTO journal SELECT 'car' || :client_id, :seq, frame FROM bench_frame ON CONFLICT (stream, seq) DO UPDATE SET frame = excluded.frame;
UPDATE streams SET last_write = 0, bytes = bytes + 100000, client = 'bench' WHERE stream = 'car' || :client_id;
COMMIT;
"""


def server(cluster: PgCluster, url: str, frame_bytes: int, clients: list[int], seconds: float) -> list[dict]:
    """pgbench running a frame's commit a transaction at each client count: commits/s, WAL MB/s."""
    import psycopg

    from occvo_services.store.factory import open_store

    open_store(url).close()  # the store's schema
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("CREATE TABLE bench_frame (digest BYTEA, pose BYTEA, frame BYTEA)")
        conn.execute("ALTER TABLE bench_frame ALTER COLUMN frame SET STORAGE EXTERNAL")
        rnd = np.random.default_rng(0)  # incompressible, as packed frames are nearly
        conn.execute(
            "INSERT INTO bench_frame VALUES (%s, %s, %s)",
            (rnd.bytes(16), np.eye(4).tobytes(), rnd.bytes(frame_bytes)),
        )
        conn.execute(  # a held lease for each client's stream, as a fenced worker writes
            "INSERT INTO leases SELECT 'car' || i, 'bench', 1, now() + interval '1 day' FROM generate_series(0, %s) i",
            (max(clients),),
        )
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "frame.sql"
        script.write_text(FRAME_SQL)
        for n in clients:
            before, t0 = counters(url), time.perf_counter()
            run = subprocess.run(
                [str(BIN / "pgbench"), "-n", "-M", "prepared", "-c", str(n), "-j", str(min(n, 2)), "-T", str(int(seconds)),
                 "-f", str(script), "-h", "127.0.0.1", "-p", str(cluster.port), "-U", "postgres", url.rsplit("/", 1)[1]],
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            after, wall = counters(url), time.perf_counter() - t0
            tx = int(
                next(line for line in run.stdout.splitlines() if "transactions actually processed" in line).split()[-1]
            )
            lat = next(line for line in run.stdout.splitlines() if line.startswith("latency average"))
            out.append(_rate(n, tx, after, before, wall, float(lat.split()[3])))
    return out


def _rate(n: int, commits: int, after: dict, before: dict, wall: float, latency_ms: float) -> dict:
    return {
        "clients": n,
        "commits_per_s": round(commits / wall, 1),
        "wal_mb_per_s": round((after["wal_bytes"] - before["wal_bytes"]) / wall / 1e6, 1),
        "wal_flushes_per_s": round((after["wal_sync"] - before["wal_sync"]) / wall, 1),
        "latency_ms": round(latency_ms, 2),
    }


def _committer(url: str, stream: str, blob: bytes, seconds: float, ready, go, out) -> None:
    from occvo_services.store.factory import open_store

    store = open_store(url)
    epoch = store.acquire(stream, stream, 3600.0)
    ready.put(1)
    go.wait()
    n, t_end, lat = 0, time.perf_counter() + seconds, []
    while (t0 := time.perf_counter()) < t_end:
        store.commit_frame(stream, n, float(n), b"d" * 16, "ok", np.eye(4), blob, n == 0, epoch=epoch, client="b")
        lat.append(time.perf_counter() - t0)
        n += 1
    store.close()
    out.put((n, statistics.median(lat) * 1000.0))


def python_clients(url: str, frame_bytes: int, clients: list[int], seconds: float) -> list[dict]:
    """Processes calling the store's commit_frame as fast as it returns, each on its own stream."""
    blob = np.random.default_rng(1).bytes(frame_bytes)
    ctx, out = mp.get_context("spawn"), []
    for n in clients:
        ready, done, go = ctx.Queue(), ctx.Queue(), ctx.Event()
        procs = [
            ctx.Process(target=_committer, args=(url, f"py{n}-{i}", blob, seconds, ready, go, done)) for i in range(n)
        ]
        for p in procs:
            p.start()
        for _ in procs:
            ready.get(timeout=120)
        before, t0 = counters(url), time.perf_counter()
        go.set()
        got = [done.get(timeout=seconds + 120) for _ in procs]
        after, wall = counters(url), time.perf_counter() - t0
        for p in procs:
            p.join()
        out.append(_rate(n, sum(c for c, _ in got), after, before, wall, statistics.median(m for _, m in got)))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--clients", default="1,2,4,8,16,32", help="pgbench client counts (empty: none)")
    p.add_argument("--python-clients", default="1,2,4", help="store-code client processes (empty: none)")
    p.add_argument("--seconds", type=float, default=15.0, help="at each client count")
    p.add_argument("--frame-kb", type=float, help="journal entry size (default: the drives' median frame)")
    p.add_argument("--skip-drive", action="store_true", help="no per-frame drive through the service")
    p.add_argument("--placements", default="members,shards", help="per-frame drives: the registration placement")
    p.add_argument("--rate", type=float, default=2.0, help="per-frame drives: each car's frames a second")
    p.add_argument("--repeats", type=int, default=3, help="sweeps of the client counts (figures: their medians)")
    p.add_argument("--output", help="write the JSON here too")
    args = p.parse_args()
    if missing():
        raise SystemExit(missing())
    cluster = PgCluster()
    try:
        result: dict = {"host_cores": mp.cpu_count()}
        if not args.skip_drive:
            placements = [p for p in args.placements.split(",") if p]
            result["per_frame"] = [per_frame(cluster.new_database(), p, args.rate) for p in placements]
        frame_bytes = int(args.frame_kb * 1e3) if args.frame_kb else median_frame_bytes()
        result["journal_frame_kb"] = round(frame_bytes / 1e3, 1)
        result["pose_row_bytes"] = pose_row_bytes(cluster.new_database())
        clients = [int(c) for c in args.clients.split(",") if c]
        py = [int(c) for c in args.python_clients.split(",") if c]
        runs: dict[str, list] = {"server": [], "python": []}
        for _ in range(args.repeats):  # the sweeps interleaved, so that the host's load falls on all alike
            if clients:
                runs["server"].append(server(cluster, cluster.new_database(), frame_bytes, clients, args.seconds))
            if py:
                runs["python"].append(python_clients(cluster.new_database(), frame_bytes, py, args.seconds))
        result |= {k: medians(v) for k, v in runs.items() if v}
    finally:
        cluster.close()
    text = json.dumps(result, indent=1)
    print(text)
    if args.output:
        Path(args.output).write_text(text + "\n")


def pose_row_bytes(url: str, rows: int = 50_000) -> float:
    """What a pose row takes on disk with its primary key's index: poses of ten streams, over the rows."""
    import psycopg

    from occvo_services.store.factory import open_store

    open_store(url).close()
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute(
            "INSERT INTO poses SELECT 'car' || (i %% 10), i, i, %s, 'ok', %s FROM generate_series(1, %s) i",
            (bytes(16), np.eye(4).tobytes(), rows),
        )
        conn.execute("VACUUM ANALYZE poses")
        (size,) = conn.execute("SELECT pg_total_relation_size('poses')").fetchone()
    return round(size / rows, 1)


def medians(sweeps: list[list[dict]]) -> list[dict]:
    """Each client count's figures, the median over the sweeps."""
    return [
        {k: (v[0]["clients"] if k == "clients" else round(statistics.median(r[k] for r in v), 1)) for k in v[0]}
        for v in zip(*sweeps, strict=True)
    ]


def median_frame_bytes() -> int:
    """The journal entry of the real scenes' frames as the worker packs them (their Occ3D indices as sent)."""
    from occvo_core.grid import OCC3D_GRID
    from occvo_schemas.models import SparseOccupancy
    from occvo_services.store.blobs import pack_frame

    sizes = []
    for name in SCENES:
        for f in frames_of(name) if (DATA / name).is_dir() else []:
            tables = SparseOccupancy.from_points(f.points, f.labels, OCC3D_GRID).index_tables(OCC3D_GRID)
            sizes.append(len(pack_frame(f, tables)))
    return int(np.median(sizes)) if sizes else 100_000


if __name__ == "__main__":
    main()
