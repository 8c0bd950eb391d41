"""Dynamic object filter: single-linkage clusters of movable voxels."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.nearest import cell_sort


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
def _union(parent, i, j):
    ri, rj = _find(parent, i), _find(parent, j)
    if ri != rj:
        parent[max(ri, rj)] = min(ri, rj)


@njit(cache=CACHE, nogil=True)
def grid_clusters(points, eps):
    """Single-linkage clusters at distance eps, found through a grid of eps-sized cells (union-find). Each point's
    id is the smallest index of its cluster whatever order the pairs are joined in, so each pair is tried once
    (its own cell and the 13 cells after it), and a cell beside a point is skipped when the point is farther than
    eps from all of it."""
    n = points.shape[0]
    parent = np.arange(n)
    if n == 0:
        return parent
    lo, dims, start, order = cell_sort(points, eps)
    eps2 = eps * eps
    tol = 1e-6 * eps  # rounding of the cell bounds: never skip a cell a point might reach
    for q in range(n):
        i = order[q]
        x0, x1, x2 = points[i, 0] - lo[0], points[i, 1] - lo[1], points[i, 2] - lo[2]
        ci, cj, ck = int(x0 / eps), int(x1 / eps), int(x2 / eps)
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
                        d0 = points[i, 0] - points[j, 0]
                        d1 = points[i, 1] - points[j, 1]
                        d2 = points[i, 2] - points[j, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
                            _union(parent, i, j)
    for i in range(n):
        parent[i] = _find(parent, i)
    return parent
