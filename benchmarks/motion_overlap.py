"""How much motion a TPV-Former checkpoint's frames tell the odometry: consecutive frames' overlap by share of the
true motion, predicted against true occupancy.

    python benchmarks/motion_overlap.py --checkpoint CKPT [--seeds 2000 2001 2002 2003 2004]

For each pair of consecutive frames of each synthetic seed, frame i+1's occupied voxels of a class group are moved into
frame i by alpha times the true relative motion (alpha 0 to 1.5) and counted where frame i has a voxel of the group
(the share of frame i+1's voxels). Truth: the renderer's occupancy inside the camera mask; predicted: the network's
labels at --min-confidence (0.9) and --min-ground-confidence (0.95: the ground is kept to be measured, though the
shipped model is served without it). A group whose curve is flat from alpha 0 to 1 agrees with no motion as well as
with the true one: registration on it finds too little motion.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from occvo_core.grid import FREE, GROUND_CLASSES, MOVABLE_CLASSES, OCC3D_GRID, STATIC_CLASSES
from occvo_core.models.image_source import ImageOccupancySource
from occvo_core.models.tpvformer.predictor import OccupancyPredictor, confident_labels
from occvo_core.sim import SyntheticScene

ALPHAS = np.round(np.arange(0.0, 1.51, 0.1), 2)
GROUPS = {
    "ground": GROUND_CLASSES,
    "movable": MOVABLE_CLASSES,
    "static above ground": tuple(c for c in STATIC_CLASSES if c not in GROUND_CLASSES),
}


def overlap(a: np.ndarray, b: np.ndarray, rel: np.ndarray, classes: tuple[int, ...]) -> np.ndarray:
    """Share of b's voxels of `classes`, moved into a's frame by alpha x rel, landing on a's voxels of `classes`."""
    in_a = np.isin(a, classes)
    points = OCC3D_GRID.centres_of(np.argwhere(np.isin(b, classes)))
    out = np.zeros(len(ALPHAS))
    for k, alpha in enumerate(ALPHAS):
        idx = OCC3D_GRID.indices_of(points @ rel[:3, :3].T + alpha * rel[:3, 3])
        idx = idx[OCC3D_GRID.inside(idx)]
        out[k] = in_a[idx[:, 0], idx[:, 1], idx[:, 2]].sum() / max(1, len(points))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[2000, 2001, 2002, 2003, 2004])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--min-confidence", type=float, default=0.9)
    ap.add_argument("--min-ground-confidence", type=float, default=0.95)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    predictor = OccupancyPredictor(args.checkpoint, device="cpu")
    thresholds = args.min_confidence, args.min_ground_confidence
    curves = {(src, g): [] for src in ("truth", "predicted") for g in GROUPS}
    for seed in args.seeds:
        scene = SyntheticScene(seed=seed, frames=args.frames)
        source = ImageOccupancySource(scene, predictor)
        grids = {"truth": [], "predicted": []}
        for i in range(len(scene)):
            truth = scene.true_grid(i).copy()
            truth[~scene.camera_mask(i)] = FREE
            grids["truth"].append(truth)
            grids["predicted"].append(
                confident_labels(*predictor.predict_labels(*source.camera_frame(i)), *thresholds).numpy()
            )
        for i in range(len(scene) - 1):
            rel = np.linalg.inv(scene.gt_poses[i]) @ scene.gt_poses[i + 1]
            for (src, g), c in curves.items():
                c.append(overlap(grids[src][i], grids[src][i + 1], rel, GROUPS[g]))
        print(f"seed {seed} done", file=sys.stderr, flush=True)
    print(f"{'':10} {'group':20} {'alpha 0':>8} {'alpha 1':>8} {'best':>5}  (alpha {ALPHAS[0]:g} to {ALPHAS[-1]:g})")
    result = {}
    for (src, g), c in curves.items():
        m = np.mean(c, axis=0)
        result[f"{src}/{g}"] = [round(float(x), 3) for x in m]
        print(
            f"{src:10} {g:20} {m[0]:8.2f} {m[10]:8.2f} {ALPHAS[np.argmax(m)]:5.1f}  " + " ".join(f"{x:.2f}" for x in m)
        )
    print(json.dumps({"seeds": args.seeds, "alphas": ALPHAS.tolist(), "overlap": result}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
