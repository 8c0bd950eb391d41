"""Loop closure offline: OccVO alone on the synthetic loop, with the registration worker's eviction and restore
(tiles wholly beyond --radius go to a dict, come back within radius - tile), with and without loop closure.

    python benchmarks/loop_closure.py --frames 700 --blocks 2x2              # four laps of 563 m
    python benchmarks/loop_closure.py --frames 700 --blocks 2x2 --no-loop-closure
    python benchmarks/loop_closure.py --frames 600 --scene-frames 3600        # the first 600 frames of long_drive's scene

Prints each loop closed (where, the position error against the truth before and after, and what it cost); at each lap's reference frame (the last one more than 85 m from the start before coming back, as
long_drive.py takes them) and at the last frame: the start area's voxels (20 m tiles around the first pose, resident
and evicted), the map's working-set voxels, APE so far and the start area's precision against the true static map;
then the start area at the last frame against lap 1 (precision, 0.4 m), every loop closed, and the loop_closure
stage's time.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from _drive_truth import START_TILES, true_start_map

from occvo_core import OccVO, OccVOConfig
from occvo_core.eval import ape_rmse
from occvo_core.map_metrics import map_metrics
from occvo_core.sim import SyntheticScene
from occvo_core.working_map import tiles_near

TILE_M = 20.0


def start_area(vo: OccVO, cold: dict) -> tuple[np.ndarray, np.ndarray]:
    """The persistent voxels of the start tiles, resident or evicted (as the map service would serve them)."""
    lo = np.array([START_TILES["ix_min"], START_TILES["iy_min"]])
    hi = np.array([START_TILES["ix_max"], START_TILES["iy_max"]])
    parts = [vo.map_points(tiles=(lo, hi, TILE_M))]
    for (ix, iy), blocks in cold.items():
        if lo[0] <= ix <= hi[0] and lo[1] <= iy <= hi[1]:
            for b in blocks:
                keep = b["f"] / np.maximum(b["last"] - b["t0"] + 1, 1) > vo.config.voxel_pfilter.p_index_threshold
                parts.append((b["pos"][keep], b["label"][keep]))
    return np.concatenate([p for p, _ in parts]), np.concatenate([lab for _, lab in parts])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=700)
    ap.add_argument(
        "--scene-frames", type=int, help="build the scene this long (the town depends on it); default --frames"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blocks", default="2x2")
    ap.add_argument("--radius", type=float, default=100.0, help="working radius of the eviction, m")
    ap.add_argument("--no-loop-closure", action="store_true")
    args = ap.parse_args(argv)
    blocks = tuple(int(x) for x in args.blocks.split("x"))
    scene = SyntheticScene(seed=args.seed, frames=args.scene_frames or args.frames, route="loop", loop_blocks=blocks)
    cfg = OccVOConfig()
    cfg = cfg.model_copy(
        update={"loop_closure": cfg.loop_closure.model_copy(update={"enabled": not args.no_loop_closure})}
    )
    gt = scene.gt_poses
    away = np.linalg.norm(gt[:, :2, 3] - gt[0, :2, 3], axis=1)
    refs = [
        max(k for k in range(a, b) if away[k] > 85.0)
        for a, b in zip(scene.lap_starts[:-1], scene.lap_starts[1:])
        if b <= args.frames
    ]
    refs.append(args.frames - 1)
    truth = true_start_map(scene)
    print(f"lap {scene.lap_length_m:.0f} m, laps start at {scene.lap_starts.tolist()}, reference frames {refs}")
    vo, cold, ego, stage_ms, maps = OccVO(cfg), {}, None, [], {}
    for i in range(args.frames):
        if ego is not None and cold:  # the worker's restore: cold tiles within radius - tile of the last pose
            for k in tiles_near(cold, ego, args.radius, TILE_M):
                for block in cold.pop(k):
                    vo.restore_tiles({k: block})
        r = vo.step(scene[i])
        if r.loop_correction is not None:
            true = (np.linalg.inv(gt[0]) @ gt[i])[:3, 3]  # in the odometry's frame, the first pose's
            before = (np.linalg.inv(r.loop_correction) @ r.pose)[:3, 3]
            print(
                f"frame {i}: loop closed {away[i]:.0f} m from the start, position error {np.linalg.norm(before - true):.2f} m "
                f"-> {np.linalg.norm(r.pose[:3, 3] - true):.2f} m; search {r.timings_ms['loop_closure']:.0f} ms, "
                f"map correction and merge {r.timings_ms['voxel_pfilter']:.0f} ms",
                flush=True,
            )
        stage_ms.append(r.timings_ms.get("loop_closure", 0.0))
        for k, block in vo.evict_tiles(r.pose[:2, 3], args.radius, TILE_M).items():
            cold.setdefault(k, []).insert(0, block)  # newest first, as the worker restores them
        ego = r.pose[:2, 3].copy()
        if i in refs:
            maps[i] = start_area(vo, cold)
            vs_truth = map_metrics(*maps[i], *truth)
            print(
                f"frame {i}: start area {len(maps[i][0])} voxels, working map {len(vo.map)}, "
                f"APE {ape_rmse(gt[: i + 1], vo.poses):.2f} m, start vs true map: precision {vs_truth.precision:.3f} "
                f"completion {vs_truth.completion:.3f}",
                flush=True,
            )
    revisit = map_metrics(*maps[refs[-1]], *maps[refs[0]])
    print(
        f"start area at frame {refs[-1]} against lap 1 (frame {refs[0]}): precision {revisit.precision:.3f}, "
        f"completion {revisit.completion:.3f}"
    )
    print(
        "loops closed (frame, correction at the ego in m):",
        [
            (t, round(float(np.linalg.norm((c @ vo.poses[t - 1])[:3, 3] - vo.poses[t - 1][:3, 3])), 2))
            for t, c in vo.loop_closures
        ],
    )
    print(
        f"loop_closure stage: median {np.median(stage_ms):.1f} ms, mean {np.mean(stage_ms):.1f}, max {np.max(stage_ms):.1f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
