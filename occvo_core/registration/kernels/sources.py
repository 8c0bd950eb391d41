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
def _source_block(ijk, n, f, oi, oj, nj, nk):
    """(block of point n among the f^3 blocks of the grid, block parity); x and y blocks shifted by oi and oj
    (_block_offset), nj and nk blocks along y and z."""
    bi, bj, bk = (ijk[n, 0] + oi) // f, (ijk[n, 1] + oj) // f, ijk[n, 2] // f
    return (bi * nj + bj) * nk + bk, (bi + bj + bk) % 2


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
def _pick_blocks(ijk, ground, on, f, shape, pick, h, chosen):
    """Mark in `chosen` the source of every f^3 block, among all points (on 0), those off the ground (1) or on it
    (2); pick and h as thin_sources'."""
    oi, oj = _block_offset(shape[0], f), _block_offset(shape[1], f)
    nj, nk = (shape[1] + oj + f - 1) // f, (shape[2] + f - 1) // f
    nb = ((shape[0] + oi + f - 1) // f) * nj * nk
    picks = np.full(nb, -1, np.int64)
    for n in range(ijk.shape[0]):
        if (on == 1 and ground[n]) or (on == 2 and not ground[n]):
            continue
        b, odd = _source_block(ijk, n, f, oi, oj, nj, nk)
        p = picks[b]
        if p < 0 or (pick == 1 and odd == 1) or (pick == 2 and h[n] < h[p]):
            picks[b] = n
    for b in range(nb):
        if picks[b] >= 0:
            chosen[picks[b]] = True


@njit(cache=CACHE, nogil=True)
def thin_sources(ijk, ground, shape, wide, coarse, fine, fine_ground, pick=0):
    """The registration source sets, each one point of every factor^3 block of voxels (0: no set): one point per wide
    and per coarse block, and for fine one per fine block off the ground and per fine_ground block on it (the ground
    only holds z, roll and pitch). pick 0 (first): the block's first point in the points' order, which grid order
    makes its rear-most (lowest x); 1 (balanced): its last (front-most) in blocks of odd parity; 2 (uniform): the
    point whose cell has the smallest fixed hash, so every voxel of a block is as likely a source, the picks lean
    no way, and a frame turned about z by a multiple of 90 degrees picks the same voxels (a cell's turned copies
    share its hash and, blocks edging on the centre, lie in other blocks). Indices ascending."""
    n = ijk.shape[0]
    h = np.zeros(n, np.uint64)
    if pick == 2:
        for i in range(n):
            h[i] = _cell_hash(ijk, i, shape)
    out = []
    for f, on, f2, on2 in ((wide, 0, 0, 0), (coarse, 0, 0, 0), (fine, 1, fine_ground, 2)):
        chosen = np.zeros(n, np.bool_)
        if f > 0:
            _pick_blocks(ijk, ground, on, f, shape, pick, h, chosen)
        if f2 > 0:
            _pick_blocks(ijk, ground, on2, f2, shape, pick, h, chosen)
        out.append(np.flatnonzero(chosen))
    return out[0], out[1], out[2]
