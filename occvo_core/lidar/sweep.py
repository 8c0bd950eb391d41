"""One sweep's labelled points and voxels: box points take the box's class, ground points driveable surface, the
rest manmade; the car's own body is left out. Majority vote of the points in each voxel, as Occ3D labels voxels; for
odometry a voxel stands at the mean of its points (a sweep's rings cut a voxel anywhere: its centre would misplace
the surface by up to 0.2 m, the same way in every frame of a ring)."""

from __future__ import annotations

import numpy as np

from occvo_core.datasets.nuscenes_drive import Boxes
from occvo_core.grid import FREE, NUM_CLASSES, OCC3D_GRID, GridSpec
from occvo_core.lidar.boxes import points_in_boxes
from occvo_core.lidar.ground import ground_mask

DRIVEABLE_SURFACE, MANMADE = 11, 15
EGO_BODY = (np.array([-1.2, -1.1, -1.0]), np.array([4.3, 1.1, 2.2]))  # the nuScenes car around its rear axle


def label_points(points: np.ndarray, boxes: Boxes) -> tuple[np.ndarray, np.ndarray]:
    """Occ3D class (N,) uint8 and box index (N,), -1 for none, of ego-frame points; boxes in the same frame."""
    labels = np.full(len(points), MANMADE, np.uint8)
    labels[ground_mask(points)] = DRIVEABLE_SURFACE
    box = points_in_boxes(points, boxes)
    labels[box >= 0] = boxes.labels[box[box >= 0]]
    return labels, box


def off_the_car(points: np.ndarray) -> np.ndarray:
    """(N,) True for points that are not the ego car's own body."""
    lo, hi = EGO_BODY
    return ~np.all((points >= lo) & (points <= hi), axis=1)


def voxel_labels(points: np.ndarray, labels: np.ndarray, grid: GridSpec = OCC3D_GRID) -> np.ndarray:
    """Dense (200,200,16) uint8 grid: each voxel the most frequent class of its points (the lower class on a tie),
    FREE where no point fell."""
    idx = grid.indices_of(points)
    keep = grid.inside(idx)
    flat = np.ravel_multi_index(tuple(idx[keep].T), grid.shape)
    votes = np.bincount(flat * NUM_CLASSES + labels[keep], minlength=int(np.prod(grid.shape)) * NUM_CLASSES)
    votes = votes.reshape(-1, NUM_CLASSES)
    out = np.where(votes.any(axis=1), votes.argmax(axis=1), FREE).astype(np.uint8)
    return out.reshape(grid.shape)


def voxel_means(points: np.ndarray, grid: GridSpec = OCC3D_GRID) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (M,) of the voxels points fall in, in increasing order, and the mean point of each (M, 3)."""
    idx = grid.indices_of(points)
    keep = grid.inside(idx)
    flat = np.ravel_multi_index(tuple(idx[keep].T), grid.shape)
    occupied, inverse, count = np.unique(flat, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, points[keep, a], minlength=len(occupied)) for a in range(3)], axis=1)
    return occupied, sums / count[:, None]
