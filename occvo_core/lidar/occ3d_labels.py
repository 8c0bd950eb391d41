"""Occ3D-style ground truth of one keyframe from the drive's aggregated LiDAR: semantics (200,200,16) uint8 (17 =
free), mask_lidar and mask_camera (docs/datasets.md: the recipe and where it differs from Occ3D's)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.lidar.aggregate import SweepPoints, keyframe_points, sweep_points
from occvo_core.lidar.raycast import camera_mask, lidar_mask
from occvo_core.lidar.sweep import voxel_labels

CAMERA_RAY_STRIDE = 8  # a ray through every 8th pixel: 200x112 rays a camera, 5 cm apart at 10 m


@dataclass(frozen=True)
class Occ3DLabels:
    semantics: np.ndarray  # (200,200,16) uint8
    mask_lidar: np.ndarray  # (200,200,16) bool
    mask_camera: np.ndarray  # (200,200,16) bool

    def arrays(self) -> dict[str, np.ndarray]:
        """As Occ3D-nuScenes ships labels.npz: masks as uint8 0/1."""
        return {
            "semantics": self.semantics,
            "mask_lidar": self.mask_lidar.astype(np.uint8),
            "mask_camera": self.mask_camera.astype(np.uint8),
        }


def load_sweeps(drive: NuScenesDrive, indices) -> dict[int, SweepPoints]:
    return {j: sweep_points(drive, j) for j in indices}


def keyframe_labels(drive: NuScenesDrive, sweeps: dict[int, SweepPoints], index: int) -> Occ3DLabels:
    agg = keyframe_points(drive, sweeps, index)
    semantics = voxel_labels(agg.points, agg.labels)
    return Occ3DLabels(
        semantics,
        lidar_mask(agg.points, agg.origin),
        camera_mask(semantics, drive.rig(index), CAMERA_RAY_STRIDE),
    )
