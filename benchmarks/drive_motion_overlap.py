"""How much motion a camera model's frames of a real drive tell the odometry: consecutive keyframes' voxels, the later
moved into the earlier by a share (alpha) of the true motion, counted where the earlier has a voxel of the same group
(ground; everything above it). Curves for the labels and for a checkpoint's served prediction (camera mask on).
A group that overlaps best at alpha 0 agrees with no motion: registration on it finds too little.

    python benchmarks/drive_motion_overlap.py --checkpoint CKPT --keyframes 17-24
    python benchmarks/drive_motion_overlap.py --labels .train/labels-0-24 --keyframes 17-24
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.grid import FREE, GROUND_CLASSES, OCC3D_GRID, grid_to_points

ALPHAS = np.round(np.arange(0, 1.51, 0.25), 2)
GROUPS = {"ground": lambda g: np.isin(g, GROUND_CLASSES), "above": lambda g: (g != FREE) & ~np.isin(g, GROUND_CLASSES)}


def overlap(a: np.ndarray, b: np.ndarray, motion: np.ndarray, group) -> np.ndarray:
    """Share of b's group voxels landing on a's, b moved by alpha x (translation, yaw) of `motion` (b -> a)."""
    occupied = group(a)
    points, _ = grid_to_points(np.where(group(b), b, FREE))
    yaw = np.arctan2(motion[1, 0], motion[0, 0])
    out = []
    for alpha in ALPHAS:
        c, s = np.cos(alpha * yaw), np.sin(alpha * yaw)
        moved = points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + alpha * motion[:3, 3]
        ijk = np.floor((moved - np.array(OCC3D_GRID.lower)) / OCC3D_GRID.voxel_size).astype(int)
        inside = ((ijk >= 0) & (ijk < np.array(a.shape))).all(1)
        out.append(occupied[tuple(ijk[inside].T)].sum() / max(1, len(points)))
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--input", default="../shared/data/nuscenes-mini")
    ap.add_argument("--checkpoint", help="a camera model (its served prediction, camera mask on)")
    ap.add_argument("--labels", help="instead: Occ3D-style labels (make-occupancy --out), inside mask_camera")
    ap.add_argument("--keyframes", default="17-24")
    args = ap.parse_args()
    torch.set_num_threads(1)
    lo, hi = (int(x) for x in args.keyframes.split("-"))
    drive = NuScenesDrive(args.input)
    if args.labels:
        from occvo_core.models.drive_eval import labels_by_token

        labels, index = labels_by_token(args.labels, drive.name)

        def grid(i):
            semantics, mask, _ = labels.load(index[drive[i].token])
            return np.where(mask, semantics, FREE)
    else:
        from occvo_core.models.image_source import NuScenesImageSource
        from occvo_core.models.tpvformer import OccupancyPredictor

        grid = NuScenesImageSource(drive, OccupancyPredictor(args.checkpoint, device="cpu", camera_mask=True)).grid
    grids = {i: grid(i) for i in range(lo, hi + 1)}
    for name, group in GROUPS.items():
        total = sum(
            overlap(grids[i], grids[i + 1], np.linalg.inv(drive[i].ego_pose) @ drive[i + 1].ego_pose, group)
            for i in range(lo, hi)
        )
        curve = "  ".join(f"{a:g}: {v:.2f}" for a, v in zip(ALPHAS, total / (hi - lo)))
        print(f"{args.checkpoint or args.labels} {name:<6} alpha {curve}")


if __name__ == "__main__":
    main()
