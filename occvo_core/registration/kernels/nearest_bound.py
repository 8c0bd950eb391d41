"""Nearest neighbours kept across GICP iterations: a search also bounds how near any other map point lies, and while
a source has moved less than that margin since, its nearest is still the one found, with no search (the answer is
the search's own: the same point and the same squared distance, computed as the search computes it)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.nearest import _beyond_best, _nearer, nearest_in_window, square_gaps

SLACK_M = 1e-6  # far above the rounding of any distance here: the kept point is strictly nearest, no tie to break


@njit(cache=CACHE, nogil=True, inline="always")
def nearest_bounded(q, map_pos, grid, origin, dims, voxel, radius, usable, max_d2, gaps):
    """nearest_within_gaps's answer, and bound2: no usable map point but that answer lies nearer to q than
    sqrt(bound2) (0: no bound; at most max_d2). The cells read are a superset of nearest_within_gaps's: those that
    can hold a point nearer than the second best so far."""
    ci = int(np.floor(q[0] / voxel)) - origin[0]
    cj = int(np.floor(q[1] / voxel)) - origin[1]
    ck = int(np.floor(q[2] / voxel)) - origin[2]
    if min(ci, cj, ck) < radius or ci >= dims[0] - radius or cj >= dims[1] - radius or ck >= dims[2] - radius:
        best, best_d2 = nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius, usable)
        return best, best_d2, 0.0
    c = (ci * dims[1] + cj) * dims[2] + ck
    best, best_d2 = _nearer(q, map_pos, grid[c], usable, -1, np.inf)
    bound2 = max_d2  # the second best's squared distance, capped
    square_gaps(q, ci, cj, ck, origin, voxel, radius, gaps)
    for r in range(1, radius + 1):
        if _beyond_best(q, ci, cj, ck, origin, r - 1, voxel, bound2):
            break
        for di in range(-r, r + 1):
            gi = gaps[0, di + radius]
            if gi >= bound2:
                continue
            edge_i = di == -r or di == r
            for dj in range(-r, r + 1):
                gij = gi + gaps[1, dj + radius]
                if gij >= bound2:
                    continue
                base = c + (di * dims[1] + dj) * dims[2]
                step = 1 if edge_i or dj == -r or dj == r else 2 * r  # inside the ring: the z faces
                for dk in range(-r, r + 1, step):
                    if gij + gaps[2, dk + radius] < bound2:
                        m = grid[base + dk]
                        if m >= 0 and usable[m]:
                            before, before_d2 = best, best_d2
                            best, best_d2 = _nearer(q, map_pos, m, usable, best, best_d2)
                            loser_d2 = before_d2 if best != before else _d2(q, map_pos, m)
                            bound2 = min(bound2, loser_d2)
    return best, best_d2, bound2 if best >= 0 else 0.0


@njit(cache=CACHE, nogil=True, inline="always")
def _d2(q, map_pos, m):
    """Squared distance as _nearer computes it."""
    d0 = map_pos[m, 0] - q[0]
    d1 = map_pos[m, 1] - q[1]
    d2 = map_pos[m, 2] - q[2]
    return d0 * d0 + d1 * d1 + d2 * d2


@njit(cache=CACHE, nogil=True, inline="always")
def still_nearest(q, map_pos, m, searched_q, bound2, max_d2):
    """The squared distance of map point m, found nearest to searched_q with bound bound2, when it is provably still
    q's nearest within max_d2 (each other point lies at least sqrt(bound2) - |q - searched_q| from q); else -1."""
    if m < 0 or bound2 <= 0.0:
        return -1.0
    d = _d2(q, map_pos, m)
    s0, s1, s2 = q[0] - searched_q[0], q[1] - searched_q[1], q[2] - searched_q[2]
    if d <= max_d2 and math.sqrt(d) + math.sqrt(s0 * s0 + s1 * s1 + s2 * s2) + SLACK_M < math.sqrt(bound2):
        return d
    return -1.0
