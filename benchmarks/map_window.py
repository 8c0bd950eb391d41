"""A map window on a long drive's map: median CPU ms of VoxelPFilterMap.window() for a window of `--window-m` along
a straight road of voxels `--road-km` long, 32 m wide, made `--road-m-per-frame` a frame (the map a long drive leaves
where no working map pages it out). The window reads only the row blocks whose key box reaches it, so its cost
follows the window, not the map.

    python benchmarks/map_window.py [--road-km 3] [--window-m 100] [--repeats 40]"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from occvo_core.registration.kernels import use_threads
from occvo_core.registration.voxel_map import VoxelPFilterMap

VOXEL = 0.4


def road_map(road_km: float, road_m_per_frame: float) -> VoxelPFilterMap:
    m = VoxelPFilterMap(VOXEL, merge_radius_m=0.0)
    xs = (np.arange(int(road_km * 1000 / VOXEL)) + 0.5) * VOXEL
    ys = (np.arange(int(32 / VOXEL)) + 0.5) * VOXEL
    for t, part in enumerate(np.array_split(xs, max(1, int(road_km * 1000 / road_m_per_frame)))):
        x, y = np.meshgrid(part, ys, indexing="ij")
        pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.5 * VOXEL)], axis=1)
        m.merge(pts, np.zeros(len(pts), np.uint8), np.tile(np.eye(3), (len(pts), 1, 1)), t)
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--road-km", type=float, default=3.0)
    ap.add_argument("--road-m-per-frame", type=float, default=40.0)
    ap.add_argument("--window-m", type=float, default=100.0)
    ap.add_argument("--repeats", type=int, default=40)
    args = ap.parse_args(argv)
    use_threads(1)
    m = road_map(args.road_km, args.road_m_per_frame)
    mid = int(args.road_km * 1000 / 2 / VOXEL)
    lower = np.array([mid, -10, -5])
    upper = np.array([mid + int(args.window_m / VOXEL), 90, 10])
    held = len(m.window(lower, upper))  # compiles
    times = []
    for _ in range(args.repeats):
        t0 = time.thread_time()
        m.window(lower, upper)
        times.append(time.thread_time() - t0)
    print(f"map {len(m)} voxels, window {held}: {np.median(times) * 1e3:.3f} ms (CPU, median of {args.repeats})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
