"""Dynamic Object Filter: cluster the movable classes; an object whose points lie, after the coarse alignment,
more than a threshold from any movable counterpart on the other side has moved and is dropped."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def cluster_objects(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """Object id per point by single-linkage clustering at distance eps; -1 for clusters under min_points."""
    n = len(points)
    if n == 0:
        return np.zeros(0, np.int64)
    pairs = cKDTree(points).query_pairs(eps, output_type="ndarray")
    adj = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, ids = connected_components(adj, directed=False)
    sizes = np.bincount(ids)
    return np.where(sizes[ids] >= min_points, ids, -1)


def displaced_objects(points: np.ndarray, ids: np.ndarray, counterparts: np.ndarray, threshold_m: float,
                      quantile: float) -> np.ndarray:
    """Mask of points whose object is displaced: the object's `quantile` of nearest-counterpart distances > threshold."""
    moved = np.zeros(len(points), bool)
    valid = ids >= 0
    if not valid.any():
        return moved
    if len(counterparts) == 0:
        dist = np.full(len(points), np.inf)
    else:
        dist, _ = cKDTree(counterparts).query(points, distance_upper_bound=threshold_m * 4)
        dist = np.minimum(dist, threshold_m * 4)  # "far" is enough; inf would poison the quantile
    for obj in np.unique(ids[valid]):
        members = ids == obj
        if np.quantile(dist[members], quantile) > threshold_m:
            moved |= members
    return moved


@dataclass
class DynamicObjects:
    frame_moved: np.ndarray  # mask over the frame's movable points
    map_moved: np.ndarray  # mask over the map's movable voxels
    frame_objects: int
    map_objects: int


def dynamic_object_filter(frame_movable_world: np.ndarray, map_movable: np.ndarray, *, threshold_m: float,
                          cluster_eps_m: float, min_cluster_points: int, quantile: float) -> DynamicObjects:
    frame_ids = cluster_objects(frame_movable_world, cluster_eps_m, min_cluster_points)
    map_ids = cluster_objects(map_movable, cluster_eps_m, min_cluster_points)
    return DynamicObjects(
        displaced_objects(frame_movable_world, frame_ids, map_movable, threshold_m, quantile),
        displaced_objects(map_movable, map_ids, frame_movable_world, threshold_m, quantile),
        int(len(np.unique(frame_ids[frame_ids >= 0]))), int(len(np.unique(map_ids[map_ids >= 0]))),
    )
