"""How the registration worker's working map grows from lap to lap on the long loop drive: the drive's frames through
the worker's own map handling (RegistrationWorker._finish: loop closure, map update, eviction to and restore from
its SQLite store), in this process, with no Zenoh and no snapshots.

    python benchmarks/working_map.py [--frames 3600] [--seed 0] [--blocks 4x4] [--radius 100]

At the start of every lap (the same place each time) and at the end it prints the working map's rows, capacity and
live voxels, those live voxels by the lap that made them, how many of the later laps' ones lie within 0.45 m of a
lap-1 voxel of their label (a second layer beside the first), and the process RSS. Then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

warnings.filterwarnings("ignore", category=RuntimeWarning)

from occvo_core import OccVO  # noqa: E402
from occvo_core.sim import SyntheticScene  # noqa: E402
from occvo_services.os_tuning import large_blocks_from_mmap  # noqa: E402
from occvo_services.registration_worker import RegistrationWorker  # noqa: E402
from occvo_services.runtime import WorkerConfig  # noqa: E402
from occvo_services.store.blobs import frame_digest, pack_frame  # noqa: E402

LAYER_M = 0.45  # one voxel pitch and a bit: a frame's own quantisation keeps re-sightings within it


def rss_mb() -> float:
    return int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 2**20


def census(vo: OccVO, lap_starts: np.ndarray) -> dict:
    m = vo.map
    n = m._n
    alive = m.alive[:n]
    lap = np.searchsorted(lap_starts, m.born[:n][alive], side="right") - 1
    pos, labels = m.pos[:n][alive], m.label[:n][alive]
    first, later = lap == 0, lap > 0
    layered = 0
    if first.any() and later.any():
        d, j = cKDTree(pos[first]).query(pos[later], distance_upper_bound=LAYER_M)
        hit = np.isfinite(d)
        hit[hit] = labels[first][j[hit]] == labels[later][hit]
        layered = int(hit.sum())
    return {
        "rows": int(n),
        "capacity": int(len(m.pos)),
        "alive": int(alive.sum()),
        "by_lap": np.bincount(lap, minlength=len(lap_starts)).tolist(),
        "later_laps": int(later.sum()),
        "later_within_layer_of_lap1": layered,
        "rss_mb": round(rss_mb(), 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=3600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blocks", default="4x4", help="loop around NXxNY city blocks")
    ap.add_argument("--radius", type=float, default=100.0, help="working radius, m")
    args = ap.parse_args()
    large_blocks_from_mmap()  # as the worker processes run
    nx, ny = (int(v) for v in args.blocks.lower().split("x"))
    scene = SyntheticScene(seed=args.seed, frames=args.frames, route="loop", loop_blocks=(nx, ny), cache_frames=4)
    lap_starts = np.asarray(scene.lap_starts, np.int64)
    marks = {int(s): k + 1 for k, s in enumerate(lap_starts) if s < args.frames}
    marks[args.frames - 1] = "end"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        worker = RegistrationWorker(WorkerConfig(store_path=str(Path(tmp) / "r.sqlite"), working_radius_m=args.radius))
        st = worker.session_of("s").after  # the work after a pose: complete, paging
        st.restart()  # a new OccVO, as at a stream's first frame
        for i in range(args.frames):
            frame = scene[i]
            reg = st.vo.register(frame)
            worker.store.commit_frame(
                "s",
                i,
                frame.stamp,
                frame_digest(frame.points, frame.labels, frame.stamp),
                "ok",
                np.asarray(reg.pose),
                pack_frame(frame),
                new_trajectory=i == 0,
            )
            evicted = st.complete(reg, frame, i, publish=True).evicted
            if evicted or st.pager.pending_restored:
                worker.store.finish_frame("s", i, None, evicted=evicted, restored=st.pager.pending_restored)
            st.pager.restores_stored()
            if i in marks:
                row = {"frame": i, "lap": marks[i], **census(st.vo, lap_starts)}
                rows.append(row)
                print(
                    f"frame {i:5d} lap {row['lap']!s:>3}  rows {row['rows']:7d} of {row['capacity']:7d}  live "
                    f"{row['alive']:7d}  made in later laps {row['later_laps']:6d}, of them within {LAYER_M} m of "
                    f"a lap-1 voxel of their label {row['later_within_layer_of_lap1']:6d}  rss {row['rss_mb']:6.1f} MB",
                    flush=True,
                )
        worker.store.close()
    print(
        json.dumps(
            {"frames": args.frames, "seed": args.seed, "blocks": args.blocks, "radius_m": args.radius, "laps": rows}
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
