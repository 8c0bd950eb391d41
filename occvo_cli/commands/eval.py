"""occvo eval: APE (as `evo_ape kitti GT EST -a`) or RPE (as `evo_rpe kitti GT EST`) of an estimated trajectory against
ground truth, translation and rotation angle (evo's `-r trans_part` and `-r angle_deg`); TUM files associated by
stamp as evo associates them, KITTI files pose by pose."""

from __future__ import annotations

import json

import numpy as np

from occvo_core.stamp_sync import MAX_DIFF_S


def add_parser(sub) -> None:
    p = sub.add_parser("eval", help="APE (SE(3) Umeyama-aligned) or RPE of an estimate against ground truth")
    p.add_argument("--gt", required=True, help="ground-truth trajectory, KITTI or TUM")
    p.add_argument("--est", required=True, help="estimated trajectory, KITTI or TUM")
    p.add_argument(
        "--fit-time-offset",
        action="store_true",
        help="also the APE against the ground truth moved in "
        "time by the one shift (within +-250 ms) that fits best: how much of the APE is timing",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=2.0,
        help="--fit-time-offset: frames/s where a file has no stamps (KITTI); TUM files carry their own",
    )
    p.add_argument(
        "--rpe", action="store_true", help="the relative pose error (translation part) instead of APE, as evo_rpe"
    )
    p.add_argument(
        "--delta", type=float, default=1.0, help="--rpe: the distance between the poses compared (default 1)"
    )
    p.add_argument(
        "--delta-unit",
        choices=("f", "m"),
        default="f",
        help="--rpe: --delta in frames (f, default) or metres of path driven (m), as evo_rpe's --delta_unit",
    )
    p.add_argument(
        "--t-max-diff",
        type=float,
        default=MAX_DIFF_S,
        help=f"TUM files: the most seconds between associated stamps (default {MAX_DIFF_S}, as evo's --t_max_diff)",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_core.eval import ape_errors, ape_rotation_errors_deg, success

    stamps, gt, est = _paired(args)
    if args.rpe:
        return _rpe(gt, est, args)
    err = ape_errors(gt, est)
    stats = {**_stats(err), "poses": len(err), "rotation_deg": _stats(ape_rotation_errors_deg(gt, est))}
    stats["success"] = success(stats["rmse"])
    if args.fit_time_offset:
        stats.update(_time_fit(gt, est, stamps, args))
    if args.json:
        print(json.dumps(stats))
    else:
        print("APE w.r.t. translation part (m), SE(3) Umeyama alignment")
        for k in ("rmse", "mean", "median", "max"):
            print(f"{k:>8}  {stats[k]:.6f}")
        print("APE w.r.t. rotation angle (deg), the same alignment")
        for k in ("rmse", "mean", "median", "max"):
            print(f"{k:>8}  {stats['rotation_deg'][k]:.6f}")
        print(f"{'poses':>8}  {stats['poses']}\n{'success':>8}  {stats['success']} (RMSE < 5 m)")
        if args.fit_time_offset:
            print(
                f"time-fitted APE RMSE {stats['ape_rmse_time_fitted_m']:.6f} m at a shift of "
                f"{stats['time_offset_ms']:+.0f} ms ({stats['time_fit_dropped_frames']} end frames outside)"
            )
    return 0


def _paired(args) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """(stamps, gt, est) pose for pose: two TUM files associated by stamp as evo does (the nearest within
    --t-max-diff), else (a KITTI file has no stamps) pose by index, which needs as many poses in each."""
    from occvo_core.errors import ConfigError, DatasetError
    from occvo_core.stamp_sync import associate
    from occvo_core.trajectory import read_stamped_trajectory

    (gt_stamps, gt), (est_stamps, est) = read_stamped_trajectory(args.gt), read_stamped_trajectory(args.est)
    if gt_stamps is None or est_stamps is None:
        if len(gt) != len(est):
            raise DatasetError(
                args.est, f"{len(est)} poses against {len(gt)} in {args.gt} (KITTI: no stamps to associate by)"
            )
        return (gt_stamps if gt_stamps is not None else est_stamps), gt, est
    if not args.t_max_diff >= 0:
        raise ConfigError(f"--t-max-diff must be 0 or more seconds, not {args.t_max_diff}")
    i_gt, i_est = associate(gt_stamps, est_stamps, args.t_max_diff)
    if not len(i_gt):
        raise DatasetError(args.est, f"no stamp within --t-max-diff {args.t_max_diff:g} s of one in {args.gt}")
    return gt_stamps[i_gt], gt[i_gt], est[i_est]


def _time_fit(gt, est, stamps, args) -> dict:
    from occvo_core.errors import ConfigError
    from occvo_core.time_fit import fit_time_offset

    if stamps is None:
        if args.rate <= 0:
            raise ConfigError(f"--rate must be more than 0, not {args.rate}")
        stamps = np.arange(len(gt)) / args.rate
    try:
        fit = fit_time_offset(gt, est, stamps)
    except ValueError as exc:
        raise ConfigError(f"--fit-time-offset: {exc}") from None
    return {
        "ape_rmse_time_fitted_m": fit.ape_rmse_m,
        "time_offset_ms": fit.offset_ms,
        "time_fit_dropped_frames": fit.dropped_frames,
    }


def _stats(err: np.ndarray) -> dict:
    """evo's statistics of an error vector."""
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(err.mean()),
        "median": float(np.median(err)),
        "std": float(err.std()),
        "min": float(err.min()),
        "max": float(err.max()),
        "sse": float(np.sum(err**2)),
    }


def _rpe(gt, est, args) -> int:
    from occvo_core.errors import ConfigError
    from occvo_core.eval import rpe_errors, rpe_rotation_errors_deg

    try:
        err = rpe_errors(gt, est, args.delta, args.delta_unit)
    except ValueError as exc:
        raise ConfigError(f"--rpe: {exc}") from None
    unit = {"f": "frames", "m": "m"}[args.delta_unit]
    stats = {**_stats(err), "pairs": len(err), "delta": args.delta, "delta_unit": args.delta_unit}
    stats["rotation_deg"] = _stats(rpe_rotation_errors_deg(gt, est, args.delta, args.delta_unit))
    if args.json:
        print(json.dumps(stats))
    else:
        print(f"RPE w.r.t. translation part (m) for delta = {args.delta:g} ({unit})")
        for k in ("rmse", "mean", "median", "std", "min", "max", "sse"):
            print(f"{k:>8}  {stats[k]:.6f}")
        print("RPE w.r.t. rotation angle (deg)")
        for k in ("rmse", "mean", "median", "std", "min", "max", "sse"):
            print(f"{k:>8}  {stats['rotation_deg'][k]:.6f}")
        print(f"{'pairs':>8}  {stats['pairs']}")
    return 0
