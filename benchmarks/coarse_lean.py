"""Where each stage of registration lands along the track, frame by frame, on a map built at ground-truth poses.

    python benchmarks/coarse_lean.py [--scenes scene-0101 scene-0268] [--config C.json5]

For every frame t >= 2 of a real scene: the map is the frames before t merged at their ground-truth poses, the guess
is the ground truth's own constant-velocity motion, and each start is scored by its error along the true step (cm,
+ = ahead): the guess; fine GICP from the guess (no coarse stage); coarse GICP; fine GICP after it (the pipeline);
fine GICP with every frame voxel a source, 1 m pairs and 60 iterations; open3d's GICP given the same static
voxels, their covariances and the map's usable voxels. Prints a row a frame and the means over slow frames (step
< 1 m) and moving ones (> 0.3 m), then one JSON line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import open3d as o3d
from _common import benchmark_main
from _gt_map import GroundTruthMapOdometry

from occvo_core import OccVOConfig
from occvo_core.datasets import OccVOReleaseScene
from occvo_core.grid import MOVABLE_CLASSES
from occvo_core.registration.gicp import coarse_gicp, fine_gicp, register_sources
from occvo_core.registration.local_map import EgoMap, frame_window
from occvo_core.registration.preprocess import preprocess
from occvo_core.trajectory import read_kitti

COLUMNS = ("guess", "fine_only", "coarse", "coarse_fine", "every_voxel", "open3d")


def _cloud(points: np.ndarray, covs: np.ndarray) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.covariances = o3d.utility.Matrix3dVector(covs)
    return cloud


def stages(vo: GroundTruthMapOdometry, frame, t: int, guess: np.ndarray) -> dict[str, np.ndarray]:
    """Poses each stage reaches for frame t from `guess`, against vo's map (frames before t)."""
    cfg = vo.config
    p = preprocess(frame, cfg)
    local = frame_window(vo.map, guess, t, vo._margin)
    ego = EgoMap.around(local, guess, vo._margin)
    coarse = coarse_gicp(p, ego, cfg).pose
    static = ~np.isin(p.labels, MOVABLE_CLASSES)
    usable = local.usable & ~np.isin(local.labels, MOVABLE_CLASSES)
    o3d_pose = o3d.pipelines.registration.registration_generalized_icp(
        _cloud(p.points[static], p.covs[static]),
        _cloud(local.pos[usable], local.cov[usable]),
        1.0,
        guess,
        o3d.pipelines.registration.TransformationEstimationForGeneralizedICP(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60),
    ).transformation
    return {
        "guess": guess,
        "fine_only": guess @ fine_gicp(p, p.fine, ego, np.eye(4), cfg).pose,
        "coarse": guess @ coarse,
        "coarse_fine": guess @ fine_gicp(p, p.fine, ego, coarse, cfg).pose,
        "every_voxel": guess @ register_sources(p, np.arange(len(p.points)), ego, np.eye(4), 1.0, 60, cfg).pose,
        "open3d": o3d_pose,
    }


def measure(root: Path, name: str, config: OccVOConfig) -> dict:
    source = OccVOReleaseScene(root / "occupancy" / name)
    frames = [source[i] for i in range(len(source))]
    gt = read_kitti(root / "trajectory" / f"{name}.kitti")
    gt = np.linalg.inv(gt[0]) @ gt
    vo = GroundTruthMapOdometry(config, gt)
    rows = []
    for t, frame in enumerate(frames):
        if t >= 2:
            step = gt[t][:3, 3] - gt[t - 1][:3, 3]
            length = float(np.linalg.norm(step))
            if length > 0.05:
                guess = gt[t - 1] @ np.linalg.inv(gt[t - 2]) @ gt[t - 1]
                along = {
                    k: float((pose[:3, 3] - gt[t][:3, 3]) @ step / length * 100)
                    for k, pose in stages(vo, frame, t, guess).items()
                }
                rows.append({"frame": t, "step_m": round(length, 3), **{k: round(v, 1) for k, v in along.items()}})
        vo.step(frame)
    slow = [r for r in rows if r["step_m"] < 1.0]
    moving = [r for r in rows if r["step_m"] > 0.3]
    return {
        "frames": rows,
        "mean_slow_cm": {k: round(float(np.mean([r[k] for r in slow])), 1) if slow else None for k in COLUMNS},
        "mean_moving_cm": {k: round(float(np.mean([r[k] for r in moving])), 1) if moving else None for k in COLUMNS},
        "slow_frames": len(slow),
        "moving_frames": len(moving),
    }


def main(argv=None) -> int:
    return benchmark_main(argv, __doc__, measure)


if __name__ == "__main__":
    sys.exit(main())
