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


@njit(cache=CACHE, nogil=True)
def grid_clusters(points, eps):
    """Single-linkage clusters at distance eps, found through a grid of eps-sized cells (union-find)."""
    n = points.shape[0]
    parent = np.arange(n)
    if n == 0:
        return parent
    lo, dims, start, order = cell_sort(points, eps)
    eps2 = eps * eps
    for i in range(n):
        ci = int((points[i, 0] - lo[0]) / eps)
        cj = int((points[i, 1] - lo[1]) / eps)
        ck = int((points[i, 2] - lo[2]) / eps)
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    a, b, c = ci + di, cj + dj, ck + dk
                    if a < 0 or b < 0 or c < 0 or a >= dims[0] or b >= dims[1] or c >= dims[2]:
                        continue
                    cell = (a * dims[1] + b) * dims[2] + c
                    for s in range(start[cell], start[cell + 1]):
                        j = order[s]
                        if j <= i:
                            continue
                        d0 = points[i, 0] - points[j, 0]
                        d1 = points[i, 1] - points[j, 1]
                        d2 = points[i, 2] - points[j, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
                            ri, rj = _find(parent, i), _find(parent, j)
                            if ri != rj:
                                parent[max(ri, rj)] = min(ri, rj)
    for i in range(n):
        parent[i] = _find(parent, i)
    return parent
