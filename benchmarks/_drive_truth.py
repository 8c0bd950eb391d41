"""The truth of a synthetic loop drive's start area (long_drive.py, loop_closure.py): its static map and the cells the
cameras saw, in the odometry frame (the first pose's)."""

from __future__ import annotations

import numpy as np

from occvo_core.grid import OCC3D_GRID
from occvo_core.sim import SyntheticScene

START_TILES = dict(ix_min=-1, ix_max=0, iy_min=-1, iy_max=0)  # 20 m tiles: [-20, 20) m around the first pose


def true_start_map(scene: SyntheticScene, near_m: float = 80.0) -> tuple[np.ndarray, np.ndarray]:
    """The true static voxels of the start area seen from any frame within `near_m` of the start, in the
    odometry frame (the first pose's), cut to the START_TILES box."""
    poses = scene.gt_poses
    d = np.linalg.norm(poses[:, :2, 3] - poses[0, :2, 3], axis=1)
    pts, labels = scene.static_map(frames=np.nonzero(d <= near_m)[0])
    inv = np.linalg.inv(poses[0])
    pts = pts @ inv[:3, :3].T + inv[:3, 3]
    keep = np.all((pts[:, :2] >= -20.0) & (pts[:, :2] < 20.0), axis=1)
    return pts[keep], labels[keep]


def seen_cells(scene: SyntheticScene, poses: np.ndarray, frames, voxel: float = 0.4) -> np.ndarray:
    """Keys of the 0.4 m cells of the start box (odometry frame) that some camera saw in `frames`, free cells
    included, placed by the odometry's own poses: where a map built from those frames could have voxels."""
    keys = []
    for i in frames:
        pts = OCC3D_GRID.centres_of(np.argwhere(scene.camera_mask(int(i))))
        pts = pts @ poses[i][:3, :3].T + poses[i][:3, 3]
        keys.append(cell_keys(pts[np.all((pts[:, :2] >= -20.4) & (pts[:, :2] < 20.4), axis=1)], voxel))
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)


def cell_keys(points: np.ndarray, voxel: float = 0.4) -> np.ndarray:
    c = np.floor(np.asarray(points) / voxel).astype(np.int64) + 1024  # the start box is +-60 cells, heights +-20
    return (c[:, 0] << 22) | (c[:, 1] << 11) | c[:, 2]
