"""The global semantic map with the Voxel PFilter: per voxel, t0 (first frame seen) and f (frames seen);
p-index = f / (t - t0) at frame t; only voxels with p-index above the threshold constrain registration."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.grid import NUM_CLASSES
from occvo_core.registration import kernels


@dataclass
class LocalMap:
    """Map voxels of a window, with a dense index grid over their integer keys for neighbour lookups."""

    rows: np.ndarray  # map rows of these voxels
    pos: np.ndarray
    cov: np.ndarray
    labels: np.ndarray
    grid: np.ndarray
    origin: np.ndarray
    dims: np.ndarray
    voxel: float

    def __len__(self) -> int:
        return len(self.rows)

    def nearest(self, queries: np.ndarray, radius_cells: int) -> tuple[np.ndarray, np.ndarray]:
        """(distance, local index or -1) of each query's nearest voxel within radius_cells voxels."""
        return kernels.nearest_distances(np.ascontiguousarray(queries, np.float64), self.pos, self.grid,
                                         self.origin, self.dims, self.voxel, radius_cells)


class VoxelPFilterMap:
    def __init__(self, voxel_m: float = 0.4, p_index_threshold: float = 0.5, pfilter: bool = True,
                 merge_radius_m: float | None = None):
        self.voxel = float(voxel_m)
        self.merge_radius = 0.5 * self.voxel if merge_radius_m is None else float(merge_radius_m)
        self.p_index_threshold = float(p_index_threshold)
        self.pfilter = pfilter
        self._n = 0
        self._alloc(1 << 16)

    def _alloc(self, capacity: int) -> None:
        old = getattr(self, "pos", None)
        fields = {
            "keys": ((capacity, 3), np.int32, 0), "pos": ((capacity, 3), np.float64, 0.0),
            "cov": ((capacity, 3, 3), np.float64, 0.0), "counts": ((capacity, NUM_CLASSES), np.int32, 0),
            "label": ((capacity,), np.uint8, 0), "t0": ((capacity,), np.int32, 0), "f": ((capacity,), np.int32, 0),
            "last": ((capacity,), np.int32, -1), "wacc": ((capacity,), np.float64, 0.0), "alive": ((capacity,), np.bool_, False),
        }
        for name, (shape, dtype, fill) in fields.items():
            arr = np.full(shape, fill, dtype)
            if old is not None:
                arr[: self._n] = getattr(self, name)[: self._n]
            setattr(self, name, arr)

    def __len__(self) -> int:
        return int(np.count_nonzero(self.alive[: self._n]))

    def copy(self) -> "VoxelPFilterMap":
        other = VoxelPFilterMap(self.voxel, self.p_index_threshold, self.pfilter, self.merge_radius)
        other._n = self._n
        for name in ("keys", "pos", "cov", "counts", "label", "t0", "f", "last", "wacc", "alive"):
            setattr(other, name, getattr(self, name).copy())
        return other

    def p_index(self, t: int) -> np.ndarray:
        """p-index of every row at frame t (f counts frames before t; t0 < t for every existing voxel)."""
        n = self._n
        return self.f[:n] / np.maximum(t - self.t0[:n], 1)

    def window(self, lower: np.ndarray, upper: np.ndarray, t: int | None = None, classes: np.ndarray | None = None) -> LocalMap:
        """Voxels with keys in [lower, upper]; with t given and the filter on, only those with p-index > threshold."""
        n = self._n
        keys = self.keys[:n]
        mask = self.alive[:n] & np.all(keys >= lower, axis=1) & np.all(keys <= upper, axis=1)
        if t is not None and self.pfilter:
            mask &= self.p_index(t) > self.p_index_threshold
        if classes is not None:
            mask &= np.isin(self.label[:n], classes)
        rows = np.flatnonzero(mask)
        return self._local(rows, lower, upper)

    def _local(self, rows: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> LocalMap:
        origin = np.asarray(lower, np.int64)
        dims = np.asarray(upper, np.int64) - origin + 1
        grid = kernels.window_grid(self.keys[rows].astype(np.int64), origin, dims)
        return LocalMap(rows, self.pos[rows], self.cov[rows], self.label[rows], grid, origin, dims, self.voxel)

    def merge(self, points_world: np.ndarray, labels: np.ndarray, covs_world: np.ndarray, t: int) -> np.ndarray:
        """Add frame t's points (world frame) and return the map rows they landed in."""
        keys = np.floor(points_world / self.voxel).astype(np.int64)
        lower, upper = keys.min(axis=0) - 1, keys.max(axis=0) + 1
        local = self.window(lower, upper)
        rows, first_key = kernels.assign_voxels(points_world, keys, local.pos, local.grid, local.origin, local.dims,
                                                self.voxel, self.merge_radius, local.rows, self._n)
        n_new = len(first_key)
        if self._n + n_new > len(self.pos):
            self._alloc(max(2 * len(self.pos), self._n + n_new))
        new = slice(self._n, self._n + n_new)
        self.keys[new] = keys[first_key]
        self.t0[new] = t
        self.f[new] = 0
        self.last[new] = -1
        self.counts[new] = 0
        self.alive[new] = True
        self._n += n_new
        kernels.merge_points(rows, points_world, covs_world, labels.astype(np.int64), t, self.pos, self.cov, self.counts,
                             self.label, self.t0, self.f, self.last, self.wacc, self.pfilter)
        return rows

    def remove(self, rows: np.ndarray) -> None:
        """Drop voxels (the dynamic object filter's moved objects); space is reclaimed when a third is dead."""
        self.alive[rows] = False
        n = self._n
        if n and np.count_nonzero(~self.alive[:n]) > n // 3:
            keep = np.flatnonzero(self.alive[:n])
            for name in ("keys", "pos", "cov", "counts", "label", "t0", "f", "last", "wacc", "alive"):
                arr = getattr(self, name)
                arr[: len(keep)] = arr[keep]
            self.alive[len(keep): n] = False
            self._n = len(keep)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        alive = self.alive[: self._n]
        return self.pos[: self._n][alive].copy(), self.label[: self._n][alive].copy()

    def arrays(self, t: int) -> dict[str, np.ndarray]:
        """Everything a saved map holds: points, labels, t0, f, p-index at frame t."""
        alive = self.alive[: self._n]
        return {"points": self.pos[: self._n][alive], "labels": self.label[: self._n][alive],
                "t0": self.t0[: self._n][alive], "f": self.f[: self._n][alive], "p_index": self.p_index(t)[alive]}
