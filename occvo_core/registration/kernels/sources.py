"""Source selection: the points each GICP pass registers, one per block of voxels."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.turns import turn_canonical_cell


@njit(cache=CACHE, nogil=True, inline="always")
def _block_offset(size, f):
    """Shift of an axis's blocks so that a block edge lies on the grid's centre: the blocks then map onto blocks
    under a turn about z (a 2.4 m block from the grid's edge would not, 200 voxels being no multiple of 6)."""
    return (f - (size // 2) % f) % f


@njit(cache=CACHE, nogil=True, inline="always")
def _cell_hash(ijk, n, shape):
    """A fixed pseudo-random number of point n's grid cell (splitmix64 of its index, the index taken up to turns about
    z): picks by it favour no direction, and a turned frame picks the same voxels."""
    cell = turn_canonical_cell(ijk[n, 0], ijk[n, 1], shape) * shape[2] + ijk[n, 2]
    z = np.uint64(cell) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=CACHE, nogil=True)
def _block_tables(shape, factors):
    """For each factor (0: none), the block of every voxel along each axis (x and y shifted by _block_offset), the
    blocks along y and z, and where its blocks start among all factors' blocks. Looked up per point: three integer
    divisions a point and factor cost more than the whole rest of a pick."""
    axis = np.zeros((len(factors), 3, max(shape[0], shape[1], shape[2])), np.int64)
    nj, nk, first = (
        np.ones(len(factors), np.int64),
        np.ones(len(factors), np.int64),
        np.zeros(len(factors) + 1, np.int64),
    )
    for q in range(len(factors)):
        f = factors[q]
        first[q + 1] = first[q]
        if f == 0:
            continue
        for a in range(3):
            offset = _block_offset(shape[a], f) if a < 2 else 0
            for v in range(shape[a]):
                axis[q, a, v] = (v + offset) // f
        nj[q], nk[q] = axis[q, 1, shape[1] - 1] + 1, axis[q, 2, shape[2] - 1] + 1
        first[q + 1] += (axis[q, 0, shape[0] - 1] + 1) * nj[q] * nk[q]
    return axis, nj, nk, first


@njit(cache=CACHE, nogil=True)
def thin_sources(ijk, ground, shape, wide, coarse, fine, fine_ground, pick=0):
    """The registration source sets, each one point of every factor^3 block of voxels (0: no set): one point per wide
    and per coarse block, and for fine one per fine block off the ground and per fine_ground block on it (the ground
    only holds z, roll and pitch). pick 0 (first): the block's first point in the points' order, which grid order
    makes its rear-most (lowest x); 1 (balanced): its last (front-most) in blocks of odd parity; 2 (uniform): the
    point whose cell has the smallest fixed hash, so every voxel of a block is as likely a source, the picks lean
    no way, and a frame turned about z by a multiple of 90 degrees picks the same voxels (a cell's turned copies
    share its hash and, blocks edging on the centre, lie in other blocks). Indices ascending. One pass over the
    points picks for all four block grids."""
    n = ijk.shape[0]
    factors = np.array([wide, coarse, fine, fine_ground], np.int64)
    on = (0, 0, 1, 2)  # the points a grid picks among: all, those off the ground, those on it
    axis, nj, nk, first = _block_tables(shape, factors)
    picks = np.full(first[-1], -1, np.int32)  # half the bytes of int64: the blocks outnumber the points
    h = np.zeros(n, np.uint64)
    if pick == 2:
        for m in range(n):
            h[m] = _cell_hash(ijk, m, shape)
    for m in range(n):
        for q in range(4):
            if factors[q] == 0 or (on[q] == 1 and ground[m]) or (on[q] == 2 and not ground[m]):
                continue
            bi, bj, bk = axis[q, 0, ijk[m, 0]], axis[q, 1, ijk[m, 1]], axis[q, 2, ijk[m, 2]]
            b = first[q] + (bi * nj[q] + bj) * nk[q] + bk
            if picks[b] < 0 or (pick == 1 and (bi + bj + bk) % 2 == 1) or (pick == 2 and h[m] < h[picks[b]]):
                picks[b] = m
    chosen = np.zeros((3, n), np.bool_)  # fine's two grids pick among disjoint points into one set
    for q in range(4):
        for b in range(first[q], first[q + 1]):
            if picks[b] >= 0:
                chosen[min(q, 2), picks[b]] = True
    return np.flatnonzero(chosen[0]), np.flatnonzero(chosen[1]), np.flatnonzero(chosen[2])
