"""Calibration of the synthetic noise against the OCC-VO sample (the paper's network-predicted occupancy).

For consecutive frames, moved into one frame by the ground-truth poses: the share of static voxels within 25 m
that lie within 0.4 m of the previous frame's static voxels (geometric consistency), and the share of those
matched within 0.3 m that keep their class (label consistency). Prints the medians-of-scenes for the sample
and for synthetic scenes under each noise preset.

    python benchmarks/noise_calibration.py [--seeds 0 1 2] [--presets none default heavy]
"""

from __future__ import annotations

import argparse

import numpy as np
from _common import SAMPLE
from scipy.spatial import cKDTree

from occvo_core.grid import STATIC_CLASSES


def consistency(source, poses, r_max: float = 25.0) -> tuple[float, float]:
    geo, lab = [], []
    for i in range(len(source) - 1):
        a, b = source[i], source[i + 1]
        ka, kb = np.isin(a.labels, STATIC_CLASSES), np.isin(b.labels, STATIC_CLASSES)
        rel = np.linalg.inv(poses[i]) @ poses[i + 1]
        pb = b.points[kb] @ rel[:3, :3].T + rel[:3, 3]
        near = np.hypot(pb[:, 0], pb[:, 1]) < r_max
        d, j = cKDTree(a.points[ka]).query(pb[near])
        geo.append(np.mean(d <= 0.41))
        m = d < 0.3
        lab.append(np.mean(a.labels[ka][j[m]] == b.labels[kb][near][m]))
    return float(np.mean(geo)), float(np.mean(lab))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--presets", nargs="+", default=["none", "default", "heavy"])
    args = ap.parse_args()
    from occvo_core.datasets import OccVOReleaseScene
    from occvo_core.sim import SyntheticScene

    scenes = sorted((SAMPLE / "occupancy").glob("scene-*")) if SAMPLE.is_dir() else []
    for d in scenes:
        s = OccVOReleaseScene(d)
        g, l = consistency(s, s.gt_poses)
        print(f"sample {d.name:22s} geometric {g:.3f}  label {l:.3f}")
    if not scenes:
        print(f"(no sample at {SAMPLE}: synthetic numbers only)")
    for preset in args.presets:
        rows = [consistency(s, s.gt_poses) for s in (SyntheticScene(seed, noise=preset) for seed in args.seeds)]
        g, l = np.median(rows, axis=0)
        print(f"synthetic noise={preset:14s} geometric {g:.3f}  label {l:.3f}  (median of seeds {args.seeds})")


if __name__ == "__main__":
    main()
