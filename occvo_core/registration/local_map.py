"""The map around a frame: the window of map voxels it can reach (LocalMap, world coordinates) and the same voxels
in the frame of a predicted ego pose (EgoMap), where GICP runs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from occvo_core.grid import NUM_CLASSES, OCC3D_GRID
from occvo_core.registration.ego_buffers import EgoBuffers
from occvo_core.registration.kernels.covariance import rigid_motions
from occvo_core.registration.kernels.map_window import ego_points_into, empty_grid, pool_voxels
from occvo_core.registration.kernels.nearest import nearest_distances

if TYPE_CHECKING:
    from occvo_core.registration.voxel_map import VoxelPFilterMap

GRID_CORNERS = np.array(np.meshgrid(*zip(OCC3D_GRID.lower, OCC3D_GRID.upper), indexing="ij")).reshape(3, -1).T
EGO_LOWER, EGO_UPPER = np.array(OCC3D_GRID.lower), np.array(OCC3D_GRID.upper)
GRID_PAD = 2  # empty cells around an EgoMap's grid: GICP's searches of up to two rings need no bounds checks


def transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points moved by a 4x4 pose."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def window_margin(margin_m: float) -> np.ndarray:
    """Margin of the window around the frame's box, x y z: the ground does not move 4 m up between frames."""
    return np.array([margin_m, margin_m, min(margin_m, 1.0)])


def frame_window(
    voxel_map: VoxelPFilterMap, pose: np.ndarray, t: int, margin: np.ndarray, tight: bool = False
) -> LocalMap:
    """The map voxels a frame can reach from `pose`: its grid's box in the world, with a margin for the correction
    registration will make (tight: see VoxelPFilterMap.window)."""
    corners = transform(pose, GRID_CORNERS)
    lower = np.floor((corners.min(axis=0) - margin) / voxel_map.voxel).astype(np.int64)
    upper = np.floor((corners.max(axis=0) + margin) / voxel_map.voxel).astype(np.int64)
    return voxel_map.window(lower, upper, t, tight)


@dataclass
class LocalMap:
    """The map voxels of a window, with a dense index grid over their integer keys for neighbour lookups.
    `usable` says which of them registration may pair with (the voxel pfilter's reliable ones, less moved objects)."""

    rows: np.ndarray  # map rows of these voxels
    pos: np.ndarray
    labels: np.ndarray
    p_index: np.ndarray
    usable: np.ndarray
    grid: np.ndarray
    origin: np.ndarray
    dims: np.ndarray
    voxel: float
    map: VoxelPFilterMap  # the map these rows belong to (covariances are read from it on demand)

    def __len__(self) -> int:
        return len(self.rows)

    def padded_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin, dims) of the whole grid (EgoMap's has a pad)."""
        return self.origin, self.dims

    @property
    def cov(self) -> np.ndarray:
        return self.map.cov[self.rows]

    def alive(self) -> np.ndarray:
        """Which of the window's voxels are still in the map (the dynamic object filter may have dropped some)."""
        return self.map.alive[self.rows]

    def contains(self, keys: np.ndarray) -> bool:
        return bool(
            len(keys) == 0
            or (np.all(keys.min(axis=0) >= self.origin) and np.all(keys.max(axis=0) < self.origin + self.dims))
        )

    def cells(self, keys: np.ndarray) -> np.ndarray:
        """Index into `grid` of each voxel key (keys inside the window)."""
        return ((keys - self.origin) * [self.dims[1] * self.dims[2], self.dims[2], 1]).sum(axis=1)

    def nearest(
        self, queries: np.ndarray, radius_cells: int, usable: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(distance, local index or -1) of each query's nearest usable voxel (or of `usable`) within radius_cells."""
        return nearest_distances(
            np.ascontiguousarray(queries, np.float64),
            self.pos,
            self.grid,
            self.origin,
            self.dims,
            self.voxel,
            radius_cells,
            self.usable if usable is None else usable,
        )


def _ego_box(lower: np.ndarray, upper: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin, dims) in cells of voxel of the box lower..upper of the ego frame. Where the box is symmetric about
    the ego in x or y, so are its cells (the ego's axis on a cell edge), whatever the quotients round to: a turned
    frame then finds the same map around it."""
    origin = np.floor(lower / voxel).astype(np.int64)
    top = np.floor(upper / voxel).astype(np.int64)
    for a in (0, 1):
        if lower[a] == -upper[a]:
            top[a] = -origin[a] - 1
    return origin, top - origin + 1


def _coarser_box(origin: np.ndarray, dims: np.ndarray, voxel: float, coarse: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin, dims) in cells of `coarse` of the cells of `voxel` origin..origin + dims: the coarse cells they
    touch, counted in whole cells where the grids nest (products of the sizes, rounded, would add a cell on one
    side of a box symmetric about the ego)."""
    ratio = coarse / voxel
    n = int(round(ratio))
    if n >= 1 and abs(ratio - n) < 1e-9:
        lo = origin // n
        return lo, -(-(origin + dims) // n) - lo
    lo = np.floor(origin * voxel / coarse).astype(np.int64)
    return lo, np.floor((origin + dims) * voxel / coarse).astype(np.int64) - lo + 1


@dataclass
class EgoMap:
    """Usable map voxels moved into the frame of a predicted ego pose, on a grid aligned with that frame.

    Registration runs here: the grid is the size of the frame's own box whatever the heading (a world-aligned box
    of a frame turned 45 degrees holds twice the cells), and it stays in cache."""

    pose: np.ndarray  # the predicted ego pose these coordinates are relative to
    pos: np.ndarray
    cov: np.ndarray
    labels: np.ndarray
    usable: np.ndarray
    grid: np.ndarray
    origin: np.ndarray
    dims: np.ndarray
    voxel: float
    source: np.ndarray  # index into the LocalMap of each point (-1 for pooled points)
    weight: np.ndarray | None = None  # map voxels behind each pooled point (None: not pooled)
    votes: np.ndarray | None = None  # their label votes
    pad: int = GRID_PAD  # empty cells on every side of the box origin..origin + dims in grid

    def padded_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin, dims) of the whole grid, pad included."""
        return self.origin - self.pad, self.dims + 2 * self.pad

    def __len__(self) -> int:
        return len(self.pos)

    @classmethod
    def build(
        cls,
        local: LocalMap,
        pose: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        voxel: float,
        subset: np.ndarray | None = None,
        buffers: EgoBuffers | None = None,
    ) -> EgoMap:
        """buffers: arrays to reuse (the EgoMap built on them before is invalid from then on); None: new ones."""
        idx = np.flatnonzero(local.usable if subset is None else subset)
        origin, dims = _ego_box(np.asarray(lower, np.float64), np.asarray(upper, np.float64), voxel)
        n, n_cells = len(idx), int(np.prod(dims + 2 * GRID_PAD))
        if buffers is None:
            pos, cov, grid, cell_of = np.empty((n, 3)), np.empty((n, 3, 3)), empty_grid(n_cells), np.empty(n, np.int64)
        else:
            pos, cov, grid, cell_of = buffers.take(n, n_cells)
        ego_points_into(
            idx,
            local.rows,
            local.map.pos,
            local.map.cov,
            np.ascontiguousarray(pose[:3, :3]),
            np.ascontiguousarray(pose[:3, 3]),
            origin,
            dims,
            voxel,
            GRID_PAD,
            pos,
            cov,
            grid,
            cell_of,
        )
        return cls(pose, pos, cov, local.labels[idx], np.ones(len(idx), bool), grid, origin, dims, voxel, idx)

    @classmethod
    def around(
        cls,
        local: LocalMap,
        pose: np.ndarray,
        margin: np.ndarray,
        subset: np.ndarray | None = None,
        buffers: EgoBuffers | None = None,
    ) -> EgoMap:
        """The window's usable voxels (or `subset`) in the frame's box with the margin, at the frame's pose."""
        return cls.build(local, pose, EGO_LOWER - margin, EGO_UPPER + margin, local.map.voxel, subset, buffers)

    def pooled(self, voxel: float) -> EgoMap:
        """The same map averaged on a coarser grid (coarse GICP searches farther at the same cost). Pooling a pooled
        map again is pooling this one directly on the coarser grid (to the sums' units), when the grids nest."""
        origin, dims = _coarser_box(self.origin, self.dims, self.voxel, voxel)
        empty_w, empty_v = np.zeros(0), np.zeros((0, NUM_CLASSES), np.int32)
        pos, cov, labels, grid, weight, votes = pool_voxels(
            self.pos,
            self.cov,
            self.labels,
            self.usable,
            empty_w if self.weight is None else self.weight,
            empty_v if self.votes is None else self.votes,
            voxel,
            origin,
            dims,
            NUM_CLASSES,
            GRID_PAD,
        )
        return EgoMap(
            self.pose,
            pos,
            cov,
            labels,
            np.ones(len(pos), bool),
            grid,
            origin,
            dims,
            voxel,
            np.full(len(pos), -1),
            weight,
            votes,
        )


def moved(
    pos: np.ndarray, cov: np.ndarray, rot: np.ndarray, trans: np.ndarray, group: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Voxel positions and covariances moved rigidly, each by its own rotation (k,3,3) and translation (k,3), or by
    those of its group (indices into rot and trans)."""
    group = np.arange(len(pos)) if group is None else np.asarray(group, np.int64)
    return rigid_motions(
        np.ascontiguousarray(pos, np.float64),
        np.ascontiguousarray(cov, np.float64),
        np.ascontiguousarray(rot, np.float64),
        np.ascontiguousarray(trans, np.float64),
        group,
    )
