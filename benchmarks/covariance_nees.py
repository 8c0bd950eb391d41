"""Is the pose covariance calibrated? The mean NEES of each frame's translation relative to the one before, against
the synthetic town's exact ground truth, over seeds 100-119 (40 frames each, default noise).

For frame i: e = translation of (P[i-1]^-1 P[i]) minus the ground truth's, C = its covariance from both frames'
covariances (occvo_core/registration/pose_covariance.py: relative_translation_covariance), NEES = e^T C^-1 e. With
calibrated covariances each NEES is chi-square with 3 degrees of freedom, and the mean of N of them lies in the 95%
interval of chi-square(3N)/N. Frames where a loop closed (their pose jumps) are left out.

    python benchmarks/covariance_nees.py [--seeds 100 101 ...] [--frames 40] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from scipy.stats import chi2

from occvo_core import OccVO, OccVOConfig
from occvo_core.registration.pose_covariance import relative_translation_nees
from occvo_core.sim import SyntheticScene


def seed_nees(seed: int, frames: int = 40, threads: int = 1) -> np.ndarray:
    """The NEES of every frame of one synthetic drive that has one."""
    scene = SyntheticScene(seed=seed, frames=frames)
    vo = OccVO(OccVOConfig(), threads=threads)
    vo.reset()
    covs = []
    for i in range(len(scene)):
        result = vo.step(scene[i])
        covs.append(result.covariance if result.loop_correction is None else None)
    return relative_translation_nees(scene.gt_poses[vo.frame_indices], vo.poses, covs)


def interval(n: int) -> tuple[float, float]:
    lo, hi = chi2.ppf([0.025, 0.975], 3 * n) / n
    return float(lo), float(hi)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(100, 120)))
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    start = time.perf_counter()
    per_seed = {s: seed_nees(s, args.frames, args.threads) for s in args.seeds}
    nees = np.concatenate(list(per_seed.values()))
    lo, hi = interval(len(nees))
    report = {
        "seeds": args.seeds,
        "frames_per_seed": args.frames,
        "N": len(nees),
        "mean_nees": float(nees.mean()),
        "interval_95": [lo, hi],
        "calibrated": bool(lo <= nees.mean() <= hi),
        "median_nees": float(np.median(nees)),
        "nees_quantiles_90_99": [float(q) for q in np.quantile(nees, [0.9, 0.99])],
        "chi2_3_quantiles_90_99": [float(q) for q in chi2.ppf([0.9, 0.99], 3)],
        "mean_nees_per_seed": {s: round(float(v.mean()), 3) for s, v in per_seed.items()},
        "seconds": round(time.perf_counter() - start, 1),
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
