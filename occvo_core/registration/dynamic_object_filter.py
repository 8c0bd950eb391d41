"""Dynamic Object Filter: cluster the movable classes; an object whose points lie, after the coarse alignment,
more than a threshold from any movable counterpart on the other side has moved and is dropped."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.config import DynamicObjectFilterConfig
from occvo_core.grid import OCC3D_GRID
from occvo_core.registration.kernels.clusters import displaced, grid_clusters, in_box, of_classes
from occvo_core.registration.local_map import LocalMap, transform
from occvo_core.registration.preprocess import MOVABLE, Prepared

EGO_LOWER, EGO_SHAPE = np.array(OCC3D_GRID.lower), np.array(OCC3D_GRID.shape)


def cluster_objects(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """Object id per point by single-linkage clustering at distance eps; -1 for clusters under min_points."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    ids = grid_clusters(np.ascontiguousarray(points, np.float64), float(eps))
    sizes = np.bincount(ids, minlength=len(points))
    return np.where(sizes[ids] >= min_points, ids, -1)


def displaced_objects(
    points: np.ndarray, ids: np.ndarray, counterparts: np.ndarray, threshold_m: float, quantile: float
) -> np.ndarray:
    """Mask of points whose object is displaced: the object's `quantile` of nearest-counterpart distances > threshold."""
    return displaced(
        np.ascontiguousarray(points, np.float64),
        np.ascontiguousarray(ids, np.int64),
        np.ascontiguousarray(counterparts, np.float64).reshape(-1, 3),
        float(threshold_m),
        float(quantile),
    )


def count_objects(ids: np.ndarray) -> int:
    """Objects among cluster_objects' ids: each is numbered by its smallest point index."""
    return int(np.count_nonzero(ids == np.arange(len(ids))))


@dataclass
class DynamicObjects:
    frame_moved: np.ndarray  # mask over the frame's movable points
    map_moved: np.ndarray  # mask over the map's movable voxels
    frame_objects: int
    map_objects: int


def dynamic_object_filter(
    frame_movable_world: np.ndarray,
    map_movable: np.ndarray,
    *,
    threshold_m: float,
    cluster_eps_m: float,
    min_cluster_points: int,
    quantile: float,
) -> DynamicObjects:
    frame_ids = cluster_objects(frame_movable_world, cluster_eps_m, min_cluster_points)
    map_ids = cluster_objects(map_movable, cluster_eps_m, min_cluster_points)
    return DynamicObjects(
        displaced_objects(frame_movable_world, frame_ids, map_movable, threshold_m, quantile),
        displaced_objects(map_movable, map_ids, frame_movable_world, threshold_m, quantile),
        count_objects(frame_ids),
        count_objects(map_ids),
    )


def find_moved_objects(
    frame: Prepared, pose: np.ndarray, local: LocalMap, config: DynamicObjectFilterConfig
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The box of Fig. 2 at the coarse pose: (mask of frame points kept for fine GICP, mask of the window's voxels of
    moved objects, counts)."""
    keep = np.ones(len(frame.points), bool)
    map_moved = np.zeros(len(local), bool)
    if not config.enabled or len(frame.movable) == 0:
        return (
            keep,
            map_moved,
            {
                "dynamic_frame_objects": 0,
                "dynamic_map_objects": 0,
                "dynamic_points": 0,
                "dynamic_map_voxels_removed": 0,
            },
        )
    movable_world = transform(pose, frame.points[frame.movable])
    # map objects are judged only where this frame can see them: inside its grid, after the coarse alignment
    candidates = of_classes(local.labels, MOVABLE)
    candidates_pos = local.pos[candidates]
    in_view = in_box(transform(np.linalg.inv(pose), candidates_pos), EGO_LOWER, OCC3D_GRID.voxel_size, EGO_SHAPE)
    candidates = candidates[in_view]
    found = dynamic_object_filter(
        movable_world,
        candidates_pos[in_view],
        threshold_m=config.displacement_threshold_m,
        cluster_eps_m=config.cluster_eps_m,
        min_cluster_points=config.min_cluster_voxels,
        quantile=config.displacement_quantile,
    )
    keep[frame.movable[found.frame_moved]] = False
    map_moved[candidates[found.map_moved]] = True
    return (
        keep,
        map_moved,
        {
            "dynamic_frame_objects": found.frame_objects,
            "dynamic_map_objects": found.map_objects,
            "dynamic_points": int(found.frame_moved.sum()),
            "dynamic_map_voxels_removed": int(found.map_moved.sum()),
        },
    )
