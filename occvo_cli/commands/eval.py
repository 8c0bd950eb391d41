"""occvo eval: APE of an estimated trajectory against ground truth (as `evo_ape kitti GT EST -a`)."""

from __future__ import annotations

import json

import numpy as np


def add_parser(sub) -> None:
    p = sub.add_parser("eval", help="APE RMSE (SE(3) Umeyama-aligned) of an estimate against ground truth")
    p.add_argument("--gt", required=True, help="ground-truth trajectory, KITTI or TUM")
    p.add_argument("--est", required=True, help="estimated trajectory, KITTI or TUM")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_core.errors import DatasetError
    from occvo_core.eval import ape_errors, success
    from occvo_core.trajectory import read_trajectory

    gt, est = read_trajectory(args.gt), read_trajectory(args.est)
    if len(gt) != len(est):
        raise DatasetError(args.est, f"{len(est)} poses against {len(gt)} in {args.gt}")
    err = ape_errors(gt, est)
    stats = {"rmse": float(np.sqrt(np.mean(err ** 2))), "mean": float(err.mean()), "median": float(np.median(err)),
             "max": float(err.max()), "poses": len(err)}
    stats["success"] = success(stats["rmse"])
    if args.json:
        print(json.dumps(stats))
    else:
        print("APE w.r.t. translation part (m), SE(3) Umeyama alignment")
        for k in ("rmse", "mean", "median", "max"):
            print(f"{k:>8}  {stats[k]:.6f}")
        print(f"{'poses':>8}  {stats['poses']}\n{'success':>8}  {stats['success']} (RMSE < 5 m)")
    return 0
