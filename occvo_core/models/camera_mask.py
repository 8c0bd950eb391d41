"""The camera mask of a predicted grid, as Occ3D masks its ground truth (`mask_camera`): only the voxels some camera
ray reaches, the first occupied voxel on each ray included. A network also fills what no camera sees (the inside of
a building, the far side of a wall); those voxels are guesses bound to the ego, and registration on them finds too
little motion (docs/model.md)."""

from __future__ import annotations

import numpy as np

from occvo_core.grid import FREE, GridSpec
from occvo_core.sim.render import visible


def camera_fans(intrinsics: np.ndarray, cam_to_ego: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n, 7) rows of x, y, z, yaw, half horizontal field of view, lowest and highest elevation (ego frame, rad):
    each pinhole camera's field of view, as sim.render.visible takes it (principal points need not be centred)."""
    fans = np.empty((len(intrinsics), 7))
    for i, (k, pose) in enumerate(zip(np.asarray(intrinsics, float), np.asarray(cam_to_ego, float))):
        axis = pose[:3, 2]  # the optical axis in the ego frame
        yaw, pitch = np.arctan2(axis[1], axis[0]), np.arcsin(np.clip(axis[2], -1.0, 1.0))
        (fx, _, cx), (_, fy, cy) = k[0], k[1]
        left, right = np.arctan((cx + 0.5) / fx), np.arctan((width - 0.5 - cx) / fx)  # image u grows to the right
        up, down = np.arctan((cy + 0.5) / fy), np.arctan((height - 0.5 - cy) / fy)
        fans[i] = (*pose[:3, 3], yaw + (left - right) / 2, (left + right) / 2, pitch - down, pitch + up)
    return fans


def masked(grid: np.ndarray, spec: GridSpec, intrinsics: np.ndarray, cam_to_ego: np.ndarray, size) -> np.ndarray:
    """`grid` with every voxel outside the camera mask set free; size: the images' (width, height)."""
    out = grid.copy()
    out[~visible(grid, camera_fans(intrinsics, cam_to_ego, *size), spec.lower, spec.voxel_size)] = FREE
    return out
