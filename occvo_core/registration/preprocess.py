"""Preprocess and source selection (the paper's Fig. 2, first box): a frame's surface voxels with their GICP
covariances, and the points each GICP pass registers."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from occvo_core.config import OccVOConfig
from occvo_core.errors import InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import GROUND_CLASSES, MOVABLE_CLASSES, OCC3D_GRID
from occvo_core.registration.kernels.covariance import plane_covariances
from occvo_core.registration.kernels.grid import grid_indices, keep_rows, surface_voxels
from occvo_core.registration.kernels.sources import thin_sources
from occvo_core.registration.local_map import EGO_LOWER

SOURCE_PICKS = ("first", "balanced", "uniform")  # thin_sources' pick numbers


def class_table(classes: tuple[int, ...]) -> np.ndarray:
    """Membership of each uint8 label in `classes`, as a lookup table (a gather, where np.isin sorts)."""
    table = np.zeros(256, bool)
    table[list(classes)] = True
    return table


GROUND, MOVABLE = class_table(GROUND_CLASSES), class_table(MOVABLE_CLASSES)


@dataclass
class Prepared:
    """A frame made ready for registration: per-point GICP covariances and the downsampled source sets."""

    points: np.ndarray
    labels: np.ndarray
    covs: np.ndarray
    wide: np.ndarray  # indices of the wide-pass sources
    coarse: np.ndarray  # indices of the coarse-GICP sources
    fine: np.ndarray  # indices of the fine-GICP sources
    movable: np.ndarray  # indices of movable-class points
    index: int = 0


def _block_factor(voxel_m: float) -> int:
    """Grid voxels per side of a downsampling block of voxel_m."""
    return max(1, int(round(voxel_m / OCC3D_GRID.voxel_size)))


def preprocess(frame: OccupancyFrame, config: OccVOConfig) -> Prepared:
    """Validate the frame, keep its surface voxels (within max_range_m), estimate their covariances and pick the
    sources. Raises InvalidFrameError for a frame that does not fit the grid."""
    frame.validate()
    points = np.ascontiguousarray(frame.points, dtype=np.float64)
    shape = np.array(OCC3D_GRID.shape, np.int64)
    ijk, outside, ascending = grid_indices(points, EGO_LOWER, OCC3D_GRID.voxel_size, shape)
    if outside:
        raise InvalidFrameError(
            frame.index,
            f"{outside} points outside the occupancy grid "
            f"{OCC3D_GRID.lower}..{OCC3D_GRID.upper} (is the frame in ego coordinates?)",
        )
    labels = np.asarray(frame.labels, np.uint8)
    # the same points in any order give the same pose and map: sources are the first voxel of each block in
    # grid order, i.e. the block's rear-most (lowest ego x)
    if not ascending:
        cell = (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]
        order = np.lexsort((points[:, 2], points[:, 1], points[:, 0], labels, cell))
        points, labels, ijk = points[order], labels[order], ijk[order]
    max_range = config.max_range_m
    if max_range is not None:  # camera occupancy is least sure of what is far
        near = points[:, 0] ** 2 + points[:, 1] ** 2 <= max_range**2
        points, labels, ijk = points[near], labels[near], ijk[near]
    surface = surface_voxels(ijk, shape)
    if len(surface) < len(points):
        points, labels, ijk = keep_rows(surface, points, labels, ijk)
    g = config.gicp
    covs = plane_covariances(ijk, shape, g.k_neighbours_radius_voxels, g.covariance_epsilon, numba.get_num_threads())
    wide, coarse, fine = thin_sources(
        ijk,
        GROUND[labels],
        shape,
        _block_factor(g.wide_voxel_m) if g.wide_voxel_m > 0 else 0,
        _block_factor(g.coarse_source_voxel_m),
        _block_factor(g.source_voxel_m),
        _block_factor(g.ground_source_voxel_m),
        SOURCE_PICKS.index(g.source_pick),
    )
    return Prepared(points, labels, covs, wide, coarse, fine, np.flatnonzero(MOVABLE[labels]), frame.index)
