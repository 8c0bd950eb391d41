"""What durable state costs the registration worker, per frame and per snapshot, and what a resume costs.

    python benchmarks/durable_state.py [--scene DIR | --synthetic SEED] [--frames 40] [--snapshot-every 20]

OccVO runs over the scene in this process; after each frame the worker's store work is timed on real SQLite files in a
temporary folder: the frame commit (pose + journaled frame, one transaction) with synchronous=FULL and with NORMAL, the
state snapshot every --snapshot-every frames as the worker takes it (the lane's copy of the state, then the
snapshot writer streaming the copy into its row), the eviction check,
and at the end a resume (load the snapshot, replay the journal). Prints medians in ms, the store's sizes, and each
snapshot's peak memory (RSS above the process's before it; Linux).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from _common import SAMPLE

from occvo_core import OccVO
from occvo_core.grid import OCC3D_GRID
from occvo_schemas.models import SparseOccupancy
from occvo_services.array_pack import unpack_arrays
from occvo_services.store.blobs import frame_digest, pack_frame
from occvo_services.store.sqlite import TrajectoryStore

warnings.filterwarnings("ignore", category=RuntimeWarning)
DATA = SAMPLE / "occupancy" / "scene-0101"


def _status_mb(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


def _reset_peak_mb() -> float | None:
    """Reset this process's peak RSS (VmHWM; Linux only) and return the RSS now, or None where it cannot be."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return _status_mb("VmRSS:")
    except OSError:
        return None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default=str(DATA) if DATA.is_dir() else None)
    p.add_argument("--synthetic", type=int, default=0, help="seed of a synthetic scene when --scene is not given")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--snapshot-every", type=int, default=20)
    args = p.parse_args()
    if args.scene:
        from occvo_core.datasets import open_scene

        scene, name = open_scene(args.scene), Path(args.scene).name
    else:
        from occvo_core.sim import SyntheticScene

        scene, name = SyntheticScene(seed=args.synthetic, frames=args.frames), f"synthetic:{args.synthetic}"
    n = min(args.frames, len(scene))
    frames = [scene[i] for i in range(n)]
    t = {
        "step": [],
        "commit_full": [],
        "commit_normal": [],
        "snapshot_copy": [],
        "snapshot_write": [],
        "evict_check": [],
    }
    peaks = []  # per snapshot: MB written, peak RSS above the process's before it
    with tempfile.TemporaryDirectory() as tmp:
        full, normal = (
            TrajectoryStore(Path(tmp) / "full.sqlite", "FULL"),
            TrajectoryStore(Path(tmp) / "normal.sqlite", "NORMAL"),
        )
        vo = OccVO()
        for i, f in enumerate(frames):
            t0 = time.perf_counter()
            r = vo.step(f)
            t["step"].append(time.perf_counter() - t0)
            digest = frame_digest(f.points, f.labels, f.stamp)
            tables = SparseOccupancy.from_points(f.points, f.labels, OCC3D_GRID).index_tables(OCC3D_GRID)  # as sent
            for store, key in ((full, "commit_full"), (normal, "commit_normal")):
                t0 = time.perf_counter()
                store.commit_frame(
                    "s", i, f.stamp, digest, r.status, r.pose, pack_frame(f, tables), new_trajectory=i == 0
                )
                t[key].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            vo.evict_tiles(r.pose[:2, 3], 120.0, 20.0)
            t["evict_check"].append(time.perf_counter() - t0)
            if (i + 1) % args.snapshot_every == 0 and i + 1 < n:
                base = _reset_peak_mb()
                t0 = time.perf_counter()  # as the worker: its lane copies the state ...
                state = {k: np.array(v) for k, v in vo.state_dict(copy=False).items()}
                t["snapshot_copy"].append(time.perf_counter() - t0)
                t0 = time.perf_counter()  # ... its snapshot writer streams the copy into the row
                full.write_snapshot("s", i, state)
                t["snapshot_write"].append(time.perf_counter() - t0)
                del state
                if base is not None:
                    peaks.append((full.sizes("s")["snapshots_bytes"] / 1e6, _status_mb("VmHWM:") - base))
        sizes = full.sizes("s")
        t0 = time.perf_counter()
        snap = full.snapshot("s")  # None when the run was shorter than --snapshot-every: resume from the journal alone
        back = OccVO()
        if snap is not None:
            back.load_state_dict(unpack_arrays(snap[1]))
        journal = full.journal("s", None if snap is None else snap[0])
        for _, f in journal:
            back.step(f)
        resume_s = time.perf_counter() - t0
        assert np.array_equal(back.poses, vo.poses), "resume did not reproduce the poses"
        full.close()
        normal.close()
    med = {k: round(float(np.median(v)) * 1000, 2) for k, v in t.items() if v}
    print(
        json.dumps(
            {
                "scene": name,
                "frames": n,
                "median_ms": med,
                "map_voxels": len(vo.map),
                "snapshot_mb": round(sizes["snapshots_bytes"] / 1e6, 2),
                "journal_frame_kb": round(sizes["journal_bytes"] / max(sizes["journal_rows"], 1) / 1e3, 1),
                "resume": {"journal_frames": len(journal), "seconds": round(resume_s, 2), "poses_equal": True},
                "snapshot_peak_rss_mb": [{"state": round(a, 1), "above_before": round(b, 1)} for a, b in peaks],
            }
        )
    )


if __name__ == "__main__":
    main()
