"""Where the real scenes' error lies: along the track, registration against a map built from ground-truth poses,
and how well a time shift or a scale explains the odometry's trajectory.

    python benchmarks/along_track.py [--scenes scene-0101 scene-0268] [--config CONFIG.json5]

For each scene:
  odometry      the plain run: APE RMSE, and the sum of its step-length errors along the track;
  gt-map        each frame registered to a map built from the ground-truth poses of the frames before it, from the
                ground-truth pose as the guess: its mean along-track offset, in cm and as a share of the distance
                (what registration alone adds when nothing before it was wrong);
  open3d        the same question put to an independent GICP (open3d's), static classes only: each frame registered
                to the 3 frames before it placed at their ground-truth poses. Where both land ahead (or behind), the
                frames and the poses disagree, not our registration;
  time shift    the APE of the odometry against the ground truth moved by dt in time (interpolated), at the best
                dt in -150..150 ms;
  scale         the APE after scaling the odometry's positions, at the best scale in 0.98..1.02.
Prints a table and one JSON line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import open3d as o3d
from _common import benchmark_main, shifted
from _gt_map import GroundTruthMapOdometry

from occvo_core import OccVO, OccVOConfig
from occvo_core.datasets import OccVOReleaseScene
from occvo_core.eval import ape_rmse
from occvo_core.grid import MOVABLE_CLASSES
from occvo_core.trajectory import read_kitti

PERIOD_S = 0.5  # nuScenes keyframes, nominally


def along_errors(gt: np.ndarray, est: np.ndarray, relative_to: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step t: (error of est[t] along the ground-truth step direction, relative to relative_to[t-1]; step length)."""
    err, length = [], []
    for t in range(1, len(gt)):
        truth = np.linalg.inv(gt[t - 1]) @ gt[t]
        step = np.linalg.inv(relative_to[t - 1]) @ est[t]
        n = np.linalg.norm(truth[:3, 3])
        err.append((step[:3, 3] - truth[:3, 3]) @ (truth[:3, 3] / max(n, 1e-9)))
        length.append(n)
    return np.array(err), np.array(length)


def open3d_along_errors(frames, gt: np.ndarray, previous: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Per step t: open3d GICP of frame t's static points to frames t-previous..t-1 at their ground-truth poses,
    from the ground-truth motion; (error along the ground-truth step, step length)."""

    def cloud(frame):
        return o3d.geometry.PointCloud(
            o3d.utility.Vector3dVector(frame.points[~np.isin(frame.labels, MOVABLE_CLASSES)])
        )

    err, length = [], []
    for t in range(1, len(frames)):
        target = o3d.geometry.PointCloud()
        for j in range(max(0, t - previous), t):
            target += cloud(frames[j]).transform(np.linalg.inv(gt[t - 1]) @ gt[j])
        truth = np.linalg.inv(gt[t - 1]) @ gt[t]
        got = o3d.pipelines.registration.registration_generalized_icp(
            cloud(frames[t]),
            target.voxel_down_sample(0.4),
            1.0,
            truth,
            o3d.pipelines.registration.TransformationEstimationForGeneralizedICP(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60),
        ).transformation
        n = np.linalg.norm(truth[:3, 3])
        err.append((got[:3, 3] - truth[:3, 3]) @ (truth[:3, 3] / max(n, 1e-9)))
        length.append(n)
    return np.array(err), np.array(length)


def measure(root: Path, name: str, config: OccVOConfig | None = None) -> dict:
    source = OccVOReleaseScene(root / "occupancy" / name)
    frames = [source[i] for i in range(len(source))]
    gt = read_kitti(root / "trajectory" / f"{name}.kitti")
    gt = np.linalg.inv(gt[0]) @ gt
    config = config or OccVOConfig()
    vo = OccVO(config)
    for frame in frames:
        vo.step(frame)
    est = vo.poses
    err, length = along_errors(gt, est, est)
    moving = length > 0.3
    ref = GroundTruthMapOdometry(config, gt)
    for frame in frames:
        ref.step(frame)
    gt_err, _ = along_errors(gt, np.array(ref.estimates), gt)
    o3d_err, _ = open3d_along_errors(frames, gt)
    shifts = np.arange(-0.3, 0.3001, 0.01)
    shift_ape = [ape_rmse(shifted(gt, f), est) for f in shifts]
    scales = np.arange(0.98, 1.02001, 0.001)
    scale_ape = []
    for s in scales:
        scaled = est.copy()
        scaled[:, :3, 3] *= s
        scale_ape.append(ape_rmse(gt, scaled))
    best_shift, best_scale = int(np.argmin(shift_ape)), int(np.argmin(scale_ape))
    return {
        "ape_rmse_m": ape_rmse(gt, est),
        "odometry_along_sum_cm": float(err[moving].sum() * 100),
        "distance_m": float(length[moving].sum()),
        "gt_map_along_mean_cm": float(gt_err[moving].mean() * 100),
        "gt_map_along_share": float(gt_err[moving].sum() / length[moving].sum()),
        "gt_map_frames_ahead": int((gt_err[moving] > 0).sum()),
        "moving_frames": int(moving.sum()),
        "open3d_along_mean_cm": float(o3d_err[moving].mean() * 100),
        "open3d_along_share": float(o3d_err[moving].sum() / length[moving].sum()),
        "open3d_frames_ahead": int((o3d_err[moving] > 0).sum()),
        "best_time_shift_ms": float(shifts[best_shift] * PERIOD_S * 1e3),
        "ape_at_best_shift_m": float(shift_ape[best_shift]),
        "best_scale": float(scales[best_scale]),
        "ape_at_best_scale_m": float(scale_ape[best_scale]),
    }


def main(argv=None) -> int:
    return benchmark_main(argv, __doc__, measure)


if __name__ == "__main__":
    sys.exit(main())
