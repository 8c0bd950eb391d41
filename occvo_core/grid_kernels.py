"""Compiled single passes over a frame's voxels on the grid, for what every frame of the service goes through: its
axis tables (the client's message), its points from them and the cells in use (the digest). numpy took a dozen
passes and temporary arrays for each; these take one."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def fill_axis_tables(points, lower, voxel, shape, table, idx) -> bool:
    """idx[i, a]: the index of points[i, a] along axis a; table[a, k]: the coordinate of index k (the last point's
    where several share it). False as soon as a point is outside the grid (NaN, inf) or an index has two coordinates."""
    seen = np.zeros(table.shape, np.bool_)
    for i in range(points.shape[0]):
        for a in range(3):
            x = points[i, a]
            f = np.floor((x - lower[a]) / voxel)
            if not (f >= 0 and f < shape[a]):
                return False
            k = int(f)
            if seen[a, k] and table[a, k] != x:
                return False
            table[a, k] = x
            seen[a, k] = True
            idx[i, a] = k
    return True


@njit(cache=True, nogil=True)
def gather_points(indices, table):
    """(N,3) float64: table[a, indices[i, a]]; the indices are checked against the table's width before."""
    out = np.empty((indices.shape[0], 3), np.float64)
    for i in range(indices.shape[0]):
        for a in range(3):
            out[i, a] = table[a, indices[i, a]]
    return out


@njit(cache=True, nogil=True)
def used_cells(indices, n):
    """(3, n) bool: per axis, the indices in use; the indices are checked below n before."""
    used = np.zeros((3, n), np.bool_)
    for i in range(indices.shape[0]):
        for a in range(3):
            used[a, indices[i, a]] = True
    return used
