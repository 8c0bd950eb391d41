"""What a set of Occ3D-style labels holds: voxels of each class (all, and inside mask_camera), the masks' fractions of
the grid, occupied voxels a keyframe; the table docs/datasets.md quotes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occvo_core.grid import CLASS_NAMES, FREE, NUM_CLASSES


class LabelStats:
    def __init__(self):
        self.counts = np.zeros(NUM_CLASSES, np.int64)
        self.counts_camera = np.zeros(NUM_CLASSES, np.int64)
        self.lidar, self.camera, self.occupied = [], [], []

    def add(self, labels) -> None:
        sem = labels.semantics
        self.counts += np.bincount(sem.ravel(), minlength=NUM_CLASSES)
        self.counts_camera += np.bincount(sem[labels.mask_camera], minlength=NUM_CLASSES)
        self.lidar.append(float(labels.mask_lidar.mean()))
        self.camera.append(float(labels.mask_camera.mean()))
        self.occupied.append(int((sem != FREE).sum()))

    def summary(self) -> dict:
        return {
            "frames": len(self.occupied),
            "occupied_per_keyframe": float(np.mean(self.occupied)),
            "mask_lidar_fraction": float(np.mean(self.lidar)),
            "mask_camera_fraction": float(np.mean(self.camera)),
            "voxels": {CLASS_NAMES[c]: int(self.counts[c]) for c in range(NUM_CLASSES)},
            "voxels_in_mask_camera": {CLASS_NAMES[c]: int(self.counts_camera[c]) for c in range(NUM_CLASSES)},
        }

    def table(self, scene: str, out: Path) -> str:
        s = self.summary()
        rows = ["| class | voxels | inside mask_camera |", "|---|---|---|"]
        rows += [f"| {c} | {s['voxels'][c]:,} | {s['voxels_in_mask_camera'][c]:,} |" for c in CLASS_NAMES]
        rows.append(
            f"\n{scene}: {s['frames']} keyframes written to {out}; {s['occupied_per_keyframe']:,.0f} occupied voxels a "
            f"keyframe; mask_lidar {s['mask_lidar_fraction']:.3f}, mask_camera {s['mask_camera_fraction']:.3f} of "
            "the grid (means over the keyframes)"
        )
        return "\n".join(rows)
