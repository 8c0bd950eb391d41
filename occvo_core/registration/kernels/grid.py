"""Preprocess: a frame's voxels on the dense ego grid (indices, the surface voxels of solid objects)."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE


@njit(cache=CACHE, nogil=True)
def dense_index(ijk, shape):
    """Flat dense grid holding each point's row index (-1 = empty); points outside the grid are left out."""
    grid = np.full(shape[0] * shape[1] * shape[2], -1, np.int32)
    for n in range(ijk.shape[0]):
        i, j, k = ijk[n, 0], ijk[n, 1], ijk[n, 2]
        if 0 <= i < shape[0] and 0 <= j < shape[1] and 0 <= k < shape[2]:
            grid[(i * shape[1] + j) * shape[2] + k] = n
    return grid


@njit(cache=CACHE, nogil=True)
def surface_mask(ijk, grid, shape):
    """True for voxels with an empty face neighbour. Interior voxels of solid objects repeat every voxel, which
    gives nearest-neighbour ICP a false minimum at every grid step, and have no surface normal."""
    out = np.ones(ijk.shape[0], np.bool_)
    for n in range(ijk.shape[0]):
        i, j, k = ijk[n, 0], ijk[n, 1], ijk[n, 2]
        if i <= 0 or j <= 0 or k <= 0 or i >= shape[0] - 1 or j >= shape[1] - 1 or k >= shape[2] - 1:
            continue
        s1, s2 = shape[1] * shape[2], shape[2]
        c = (i * shape[1] + j) * shape[2] + k
        if (
            grid[c - s1] >= 0
            and grid[c + s1] >= 0
            and grid[c - s2] >= 0
            and grid[c + s2] >= 0
            and grid[c - 1] >= 0
            and grid[c + 1] >= 0
        ):
            out[n] = False
    return out


@njit(cache=CACHE, nogil=True)
def grid_indices(points, lower, voxel, shape):
    """Voxel indices floor((p - lower) / voxel) of each point, how many fall outside the grid, and whether the
    points' cells rise strictly in grid order (read in the same pass: a sorted frame needs no sort)."""
    ijk = np.empty((points.shape[0], 3), np.int64)
    outside = 0
    ascending = True
    last = np.int64(-1)
    for n in range(points.shape[0]):
        inside = True
        for a in range(3):
            v = int(np.floor((points[n, a] - lower[a]) / voxel))
            ijk[n, a] = v
            inside = inside and 0 <= v < shape[a]
        if not inside:
            outside += 1
        cell = (ijk[n, 0] * shape[1] + ijk[n, 1]) * shape[2] + ijk[n, 2]
        ascending = ascending and cell > last
        last = cell
    return ijk, outside, ascending


@njit(cache=CACHE, nogil=True)
def column_masks(ijk, shape, pad=0):
    """One bit a z level for each (i, j) column of the grid: a column's neighbourhood is read in one word. pad:
    that many empty columns around the grid and each column's bits raised by pad, so a neighbourhood `pad` voxels
    wide is read with no test for the grid's edges (an empty column adds nothing, as one outside)."""
    if shape[2] + 2 * pad > 62:
        raise ValueError("grids over 62 voxels high are not supported")
    nj = shape[1] + 2 * pad
    masks = np.zeros((shape[0] + 2 * pad) * nj, np.int64)
    for n in range(ijk.shape[0]):
        masks[(ijk[n, 0] + pad) * nj + ijk[n, 1] + pad] |= np.int64(1) << (ijk[n, 2] + pad)
    return masks


@njit(cache=CACHE, nogil=True)
def surface_voxels(ijk, shape):
    """Indices of the points that are surface voxels (surface_mask), read from the columns' occupancy bits: a few
    kB of words where the dense grid is megabytes."""
    if shape[2] > 62:
        return np.flatnonzero(surface_mask(ijk, dense_index(ijk, shape), shape))
    masks = column_masks(ijk, shape)
    out = np.empty(ijk.shape[0], np.int64)
    n_out = 0
    for n in range(ijk.shape[0]):
        i, j, k = ijk[n, 0], ijk[n, 1], ijk[n, 2]
        if 0 < i < shape[0] - 1 and 0 < j < shape[1] - 1 and 0 < k < shape[2] - 1:
            c = i * shape[1] + j
            column = masks[c]
            if (
                (column >> (k - 1))
                & (column >> (k + 1))
                & (masks[c - shape[1]] >> k)
                & (masks[c + shape[1]] >> k)
                & (masks[c - 1] >> k)
                & (masks[c + 1] >> k)
                & 1
            ):
                continue  # every face neighbour occupied: inside a solid
        out[n_out] = n
        n_out += 1
    return out[:n_out]


@njit(cache=CACHE, nogil=True)
def keep_rows(rows, points, labels, ijk):
    """points, labels and ijk at `rows`, in one pass (numpy's gathers copy each array on its own)."""
    n = rows.shape[0]
    p, l, g = np.empty((n, 3)), np.empty(n, labels.dtype), np.empty((n, 3), np.int64)
    for m in range(n):
        r = rows[m]
        for a in range(3):
            p[m, a] = points[r, a]
            g[m, a] = ijk[r, a]
        l[m] = labels[r]
    return p, l, g
