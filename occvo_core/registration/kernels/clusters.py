"""Dynamic object filter: single-linkage clusters of movable voxels, which of them are in view, which displaced."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.nearest import cell_sort, near_one


@njit(cache=CACHE, nogil=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=CACHE, nogil=True, inline="always")
def _gap(x, d, cell, eps, tol):
    """Lower bound on the distance along one axis from offset x in its cell to the cell d (-1, 0, 1) beside it."""
    if d == 0:
        return 0.0
    g = (cell + 1) * eps - x if d > 0 else x - cell * eps
    return max(g - tol, 0.0)


@njit(cache=CACHE, nogil=True)
def grid_clusters(points, eps):
    """Single-linkage clusters at distance eps, found through a grid of eps-sized cells (union-find). Each point's
    id is the smallest index of its cluster whatever order the pairs are joined in (a root is always its set's
    smallest index), so each pair is tried once (its own cell and the 13 cells after it), and a cell beside a point
    is skipped when the point is farther than eps from all of it. The points are read in a copy in cell order."""
    n = points.shape[0]
    parent = np.arange(n)
    if n == 0:
        return parent
    lo, dims, start, order = cell_sort(points, eps)
    by_cell = np.empty((n, 3))
    for s in range(n):
        by_cell[s, 0], by_cell[s, 1], by_cell[s, 2] = points[order[s], 0], points[order[s], 1], points[order[s], 2]
    eps2 = eps * eps
    tol = 1e-6 * eps  # rounding of the cell bounds: never skip a cell a point might reach
    for q in range(n):
        p0, p1, p2 = by_cell[q, 0], by_cell[q, 1], by_cell[q, 2]
        x0, x1, x2 = p0 - lo[0], p1 - lo[1], p2 - lo[2]
        ci, cj, ck = int(x0 / eps), int(x1 / eps), int(x2 / eps)
        root = _find(parent, order[q])  # kept up to date below: only this point's unions move it
        for di in range(0, 2):
            g0 = _gap(x0, di, ci, eps, tol)
            for dj in range(-1 if di > 0 else 0, 2):
                g1 = _gap(x1, dj, cj, eps, tol)
                for dk in range(-1 if di > 0 or dj > 0 else 0, 2):
                    a, b, c = ci + di, cj + dj, ck + dk
                    if b < 0 or c < 0 or a >= dims[0] or b >= dims[1] or c >= dims[2]:
                        continue
                    g2 = _gap(x2, dk, ck, eps, tol)
                    if g0 * g0 + g1 * g1 + g2 * g2 > eps2:
                        continue
                    cell = (a * dims[1] + b) * dims[2] + c
                    first = q + 1 if di == 0 and dj == 0 and dk == 0 else start[cell]  # own cell: the pairs after
                    for s in range(first, start[cell + 1]):
                        j = order[s]
                        if parent[j] == root:  # joined already (most pairs of an object, once it is one)
                            continue
                        d0, d1, d2 = p0 - by_cell[s, 0], p1 - by_cell[s, 1], p2 - by_cell[s, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
                            other = _find(parent, j)
                            if other != root:  # the smaller root stays
                                parent[max(root, other)] = min(root, other)
                                root = min(root, other)
    for i in range(n):
        parent[i] = _find(parent, i)
    return parent


@njit(cache=CACHE, nogil=True)
def displaced(points, ids, counterparts, radius, quantile):
    """Mask of the points whose object (ids: its smallest index, -1 for none) is displaced: no more of its points
    than the `quantile` rank have a counterpart within radius. An object is decided as soon as enough of its points
    are found near or not near, and its other points are not looked up."""
    n = points.shape[0]
    size = np.zeros(n, np.int64)
    for i in range(n):
        if ids[i] >= 0:
            size[ids[i]] += 1
    rank = np.zeros(n, np.int64)
    for o in range(n):
        if size[o] > 0:
            rank[o] = min(np.int64(np.rint(quantile * (size[o] - 1))), size[o] - 1)  # half to even, as numpy's
    near, far = np.zeros(n, np.int64), np.zeros(n, np.int64)
    if counterparts.shape[0] > 0:
        lo, dims, start, order = cell_sort(counterparts, radius)
        for i in range(n):
            o = ids[i]
            if o < 0 or near[o] > rank[o] or far[o] >= size[o] - rank[o]:
                continue
            if near_one(points[i, 0], points[i, 1], points[i, 2], counterparts, lo, dims, start, order, radius):
                near[o] += 1
            else:
                far[o] += 1
    moved = np.zeros(n, np.bool_)
    for i in range(n):
        moved[i] = ids[i] >= 0 and near[ids[i]] <= rank[ids[i]]
    return moved


@njit(cache=CACHE, nogil=True)
def in_box(points, lower, voxel, shape):
    """Which points fall in a grid's box: their voxel indices floor((p - lower) / voxel) within shape."""
    out = np.empty(points.shape[0], np.bool_)
    for n in range(points.shape[0]):
        inside = True
        for a in range(3):
            idx = np.floor((points[n, a] - lower[a]) / voxel)
            inside = inside and 0 <= idx < shape[a]
        out[n] = inside
    return out


@njit(cache=CACHE, nogil=True)
def of_classes(labels, table):
    """Indices of the labels that table marks (np.flatnonzero(table[labels]) in one pass)."""
    out = np.empty(labels.shape[0], np.int64)
    m = 0
    for i in range(labels.shape[0]):
        if table[labels[i]]:
            out[m] = i
            m += 1
    return out[:m]
