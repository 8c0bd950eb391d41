"""What a frame commit costs in each store backend: SQLite (synchronous=FULL, the default) and PostgreSQL
(synchronous_commit on, fsync on), unfenced and fenced by a lease epoch, side by side in one run.

    python benchmarks/store_backends.py [--scene DIR] [--commits 300] [--pg-url postgresql://...]

Real frames of the scene (packed as the worker journals them, with their Occ3D indices) are committed in turn to each
store, one commit of each per step, so that the machine's load falls on all alike. Without --pg-url a PostgreSQL 15
server is started in a temporary folder as the tests do (services/store/pg_local.py). Also times a snapshot write of the scene's
OccVO state after --state-frames frames. Prints JSON: median and p90 ms per backend, the ratio of the medians."""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from occvo_core import OccVO
from occvo_core.grid import OCC3D_GRID
from occvo_schemas.models import SparseOccupancy
from occvo_services.store.blobs import frame_digest, pack_frame
from occvo_services.store.factory import open_store

warnings.filterwarnings("ignore", category=RuntimeWarning)
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared/data/occvo-sample/occupancy/scene-0101"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default=str(DATA) if DATA.is_dir() else None)
    p.add_argument("--commits", type=int, default=300, help="commits per backend")
    p.add_argument("--state-frames", type=int, default=20, help="frames of OccVO before the timed snapshot")
    p.add_argument("--pg-url", help="a PostgreSQL database to use (default: a temporary server)")
    args = p.parse_args()
    if args.scene:
        from occvo_core.datasets import open_scene

        scene, name = open_scene(args.scene), Path(args.scene).name
    else:
        from occvo_core.sim import SyntheticScene

        scene, name = SyntheticScene(seed=0, frames=40), "synthetic:0"
    frames = [scene[i] for i in range(min(40, len(scene)))]
    blobs = []
    for f in frames:
        tables = SparseOccupancy.from_points(f.points, f.labels, OCC3D_GRID).index_tables(OCC3D_GRID)  # as sent
        blobs.append((f.stamp, frame_digest(f.points, f.labels, f.stamp), pack_frame(f, tables)))
    vo = OccVO()
    for f in frames[: args.state_frames]:
        vo.step(f)
    state = {k: np.array(v) for k, v in vo.state_dict(copy=False).items()}

    cluster = None
    if args.pg_url is None:
        from occvo_services.store.pg_local import PgCluster, missing

        if missing():
            raise SystemExit(missing())
        cluster = PgCluster()
        url = cluster.new_database()
    else:
        url = args.pg_url
    try:
        with tempfile.TemporaryDirectory() as tmp:
            stores = {"sqlite": open_store(Path(tmp) / "s.sqlite"), "postgresql": open_store(url)}
            epochs = {k: s.acquire("car", "bench", 3600.0) for k, s in stores.items()}
            t: dict[str, list[float]] = {f"{k}{fenced}": [] for k in stores for fenced in ("", "_fenced")}
            for i in range(args.commits):
                stamp, digest, blob = blobs[i % len(blobs)]
                for k, s in stores.items():
                    for fenced in ("", "_fenced"):
                        stream = "car" if fenced else "bus"
                        t0 = time.perf_counter()
                        s.commit_frame(
                            stream,
                            i,
                            stamp,
                            digest,
                            "ok",
                            np.eye(4),
                            blob,
                            new_trajectory=i == 0,
                            epoch=epochs[k] if fenced else None,
                        )
                        t[k + fenced].append(time.perf_counter() - t0)
            snap = {}
            for k, s in stores.items():
                t0 = time.perf_counter()
                s.write_snapshot("car", args.commits - 1, state)
                snap[k] = round((time.perf_counter() - t0) * 1000, 1)
            for s in stores.values():
                s.close()
    finally:
        if cluster is not None:
            cluster.close()
    med = {k: round(float(np.median(v)) * 1000, 3) for k, v in t.items()}
    p90 = {k: round(float(np.percentile(v, 90)) * 1000, 3) for k, v in t.items()}
    print(
        json.dumps(
            {
                "scene": name,
                "commits_per_backend": args.commits,
                "journal_frame_kb": round(float(np.mean([len(b) for *_, b in blobs])) / 1e3, 1),
                "commit_median_ms": med,
                "commit_p90_ms": p90,
                "postgresql_over_sqlite": round(med["postgresql"] / med["sqlite"], 2),
                "snapshot_mb": round(sum(a.nbytes for a in state.values()) / 1e6, 1),
                "snapshot_write_ms": snap,
            }
        )
    )


if __name__ == "__main__":
    main()
