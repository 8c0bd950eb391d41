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

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from occvo_core import OccVO, OccVOConfig  # noqa: E402
from occvo_core.datasets import OccVOReleaseScene  # noqa: E402
from occvo_core.eval import ape_rmse  # noqa: E402
from occvo_core.grid import MOVABLE_CLASSES  # noqa: E402
from occvo_core.trajectory import read_kitti  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "occvo-sample"
PERIOD_S = 0.5  # nuScenes keyframes, nominally


class GroundTruthMapOdometry(OccVO):
    """OccVO whose guess is the ground-truth pose and whose map is built at ground-truth poses; the estimate of
    each frame is kept aside in `estimates`."""

    def __init__(self, config, gt):
        self.gt, self.estimates = gt, []
        super().__init__(config)

    def _initial_guess(self, frame):
        return self.gt[len(self._poses)]

    def _commit(self, frame, pose, moved_rows, local=None, *args, **kwargs):
        self.estimates.append(pose)
        super()._commit(frame, self.gt[len(self._poses)], moved_rows, local, *args, **kwargs)


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


def shifted(gt: np.ndarray, frames: float) -> np.ndarray:
    """Ground-truth positions `frames` keyframes later (linear between keyframes, extrapolated past the ends)."""
    out = gt.copy()
    n = len(gt)
    for t in range(n):
        a = t + frames
        i = int(np.clip(np.floor(a), 0, n - 2))
        out[t, :3, 3] = gt[i, :3, 3] + (a - i) * (gt[i + 1, :3, 3] - gt[i, :3, 3])
    return out


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


def measure_scenes(argv, description: str, measure_one) -> dict | None:
    """{scene: measure_one(sample, scene, config)} for the --sample, --scenes and --config of a benchmark on the real
    scenes; None, after saying so, without the sample."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sample", type=Path, default=SAMPLE)
    ap.add_argument("--scenes", nargs="+", default=["scene-0101", "scene-0268"])
    ap.add_argument("--config", type=Path, help="odometry config (JSON5), e.g. {gicp: {source_pick: 'balanced'}}")
    args = ap.parse_args(argv)
    if not (args.sample / "occupancy").is_dir():
        print(f"no sample data at {args.sample}", file=sys.stderr)
        return None
    config = OccVOConfig.load(args.config) if args.config else OccVOConfig()
    return {name: measure_one(args.sample, name, config) for name in args.scenes}


def benchmark_main(argv, description: str, measure_one, print_scene) -> int:
    """A real-scene benchmark's main: measure_scenes, print_scene(name, result) for each, then one JSON line."""
    report = measure_scenes(argv, description, measure_one)
    if report is None:
        return 2
    for name, r in report.items():
        print_scene(name, r)
    print(json.dumps(report))
    return 0


def print_scene(name: str, r: dict) -> None:
    print(
        f"{name}: APE {r['ape_rmse_m']:.3f} m; odometry steps sum {r['odometry_along_sum_cm']:+.1f} cm along "
        f"{r['distance_m']:.1f} m\n"
        f"  gt-map registration: {r['gt_map_along_mean_cm']:+.1f} cm mean along the track "
        f"({100 * r['gt_map_along_share']:+.2f}% of the distance), ahead in {r['gt_map_frames_ahead']} of "
        f"{r['moving_frames']} moving frames\n"
        f"  open3d GICP at ground-truth poses: {r['open3d_along_mean_cm']:+.1f} cm "
        f"({100 * r['open3d_along_share']:+.2f}%), ahead in {r['open3d_frames_ahead']} of {r['moving_frames']}\n"
        f"  best time shift {r['best_time_shift_ms']:+.0f} ms: APE {r['ape_at_best_shift_m']:.3f} m; "
        f"best scale {r['best_scale']:.3f}: APE {r['ape_at_best_scale_m']:.3f} m"
    )


def main(argv=None) -> int:
    return benchmark_main(argv, __doc__, measure, print_scene)


if __name__ == "__main__":
    sys.exit(main())
