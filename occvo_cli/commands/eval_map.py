"""occvo eval-map: accuracy, precision and completion of a reconstructed map (the paper's Table IV)."""

from __future__ import annotations

import json
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("eval-map", help="map accuracy / precision / completion against a ground-truth or reference map")
    p.add_argument("--est-map", type=Path, required=True, help="reconstructed map: .npz (points, labels) or .ply")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--gt-map", type=Path, help="ground-truth map: .npz (points, labels) or .ply, same frame as --est-map"
    )
    src.add_argument(
        "--reference-scene",
        type=Path,
        help="scene folder without a true map: build the reference map from its occupancy along --gt poses",
    )
    p.add_argument("--gt", type=Path, help="ground-truth trajectory (KITTI/TUM) for --reference-scene or alignment")
    p.add_argument(
        "--est-traj",
        type=Path,
        help="estimated trajectory: move --est-map into the ground truth's frame by the APE (Umeyama) alignment",
    )
    p.add_argument("--threshold", type=float, default=0.4, help="precision / completion distance, m (default 0.4)")
    p.add_argument("--all-classes", action="store_true", help="compare every class, not only the static ones")
    p.add_argument("--save-reference", type=Path, help="write the reference map built from --reference-scene here")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_core.errors import ConfigError, DatasetError
    from occvo_core.grid import STATIC_CLASSES
    from occvo_core.map_metrics import align_to_ground_truth, load_map, map_metrics, reference_map_from_poses, save_map
    from occvo_core.trajectory import read_trajectory

    if not args.threshold > 0:
        raise ConfigError(f"--threshold must be positive, got {args.threshold}")
    est = load_map(args.est_map)
    gt_poses = read_trajectory(args.gt) if args.gt else None
    if args.gt_map:
        truth = load_map(args.gt_map)
        reference = f"ground-truth map {args.gt_map}"
    else:
        from occvo_core.datasets import open_scene

        source = open_scene(args.reference_scene, gt=args.gt)
        if source.gt_poses is None:
            raise DatasetError(args.reference_scene, "no ground-truth poses: give --gt")
        truth = reference_map_from_poses(source)
        reference = truth.kind
        gt_poses = source.gt_poses
        if args.save_reference:
            save_map(args.save_reference, truth.points, truth.labels)
    if args.reference_scene and not args.est_traj:
        raise ConfigError(
            "--reference-scene builds the reference in the ground truth's frame and --est-map is in the "
            "estimate's own: give --est-traj (the run's trajectory.kitti) to align them"
        )
    points = est.points
    if args.est_traj:
        if gt_poses is None:
            raise ConfigError("--est-traj needs --gt (or --reference-scene with poses) to align to")
        est_poses = read_trajectory(args.est_traj)
        n = min(len(est_poses), len(gt_poses))
        points = align_to_ground_truth(points, est_poses[:n], gt_poses[:n])
    _check_overlap(points, truth.points, args)
    classes = None if args.all_classes else STATIC_CLASSES
    m = map_metrics(points, est.labels, truth.points, truth.labels, args.threshold, classes, reference)
    if args.json:
        print(json.dumps(m.as_dict(), indent=2))
    else:
        print(f"reference:  {m.reference}")
        print(f"classes:    {'all' if classes is None else 'static'}   threshold {m.threshold:.2f} m")
        print(f"accuracy:   {m.accuracy:.3f} m  (RMSE of reconstructed -> ground-truth distance)")
        print(f"precision:  {m.precision:.3f}  ({m.n_reconstructed} reconstructed points)")
        print(f"completion: {m.completion:.3f}  ({m.n_ground_truth} ground-truth points)")
    return 0


OVERLAP_M = 2.0  # an estimate with no point this close to the reference is in another frame, not a poor map


def _check_overlap(est, ref, args) -> None:
    """Refuse maps that cannot be in one frame: metrics of such a pair are numbers without meaning."""
    import numpy as np
    from scipy.spatial import cKDTree

    from occvo_core.errors import ConfigError

    what = "--gt-map" if args.gt_map else "the reference built from --reference-scene"
    if len(est) == 0 or len(ref) == 0:
        raise ConfigError(f"{'--est-map' if len(est) == 0 else what} has no points")
    sample = est[np.linspace(0, len(est) - 1, min(len(est), 20_000)).astype(int)]
    near = np.isfinite(cKDTree(ref).query(sample, distance_upper_bound=OVERLAP_M)[0])
    if not near.any():
        hint = "" if args.est_traj else "; give --est-traj (and --gt) to align the estimate"
        raise ConfigError(
            f"--est-map and {what} do not overlap (no point within {OVERLAP_M:g} m of the other): "
            f"they are not in one frame{hint}"
        )
