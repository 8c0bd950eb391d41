"""Source selection: the points each GICP pass registers, one per block of voxels."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE


@njit(cache=CACHE, nogil=True, inline="always")
def _source_block(ijk, n, f, shape):
    """(block of point n among the f^3 blocks of the grid, block parity)."""
    bi, bj, bk = ijk[n, 0] // f, ijk[n, 1] // f, ijk[n, 2] // f
    return (bi * ((shape[1] + f - 1) // f) + bj) * ((shape[2] + f - 1) // f) + bk, (bi + bj + bk) % 2


@njit(cache=CACHE, nogil=True, inline="always")
def _cell_hash(ijk, n, shape):
    """A fixed pseudo-random number of point n's grid cell (splitmix64 of its index): picks by it favour no direction."""
    z = np.uint64((ijk[n, 0] * shape[1] + ijk[n, 1]) * shape[2] + ijk[n, 2]) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=CACHE, nogil=True)
def thin_sources(ijk, ground, shape, wide, coarse, fine, fine_ground, pick=0):
    """The registration source sets, each one point of every factor^3 block of voxels (0: no set): one point per wide
    and per coarse block, and for fine one per fine block off the ground and per fine_ground block on it (the ground
    only holds z, roll and pitch). pick 0 (first): the block's first point in the points' order, which grid order
    makes its rear-most (lowest x); 1 (balanced): its last (front-most) in blocks of odd parity; 2 (uniform): the
    point whose cell has the smallest fixed hash, so every voxel of a block is as likely a source and the picks lean
    no way. Indices ascending."""
    factors = (wide, coarse, fine, fine_ground)
    picks = []
    best = []
    for f in factors:
        g = max(f, 1)
        size = ((shape[0] + g - 1) // g) * ((shape[1] + g - 1) // g) * ((shape[2] + g - 1) // g)
        picks.append(np.full(size, -1, np.int32))
        best.append(np.zeros(size if pick == 2 else 1, np.uint64))
    out = np.empty((3, ijk.shape[0]), np.int64)
    count = np.zeros(3, np.int64)
    for n in range(ijk.shape[0]):
        h = _cell_hash(ijk, n, shape) if pick == 2 else np.uint64(0)
        for s in range(4):
            f = factors[s]
            if f == 0 or (s == 2 and ground[n]) or (s == 3 and not ground[n]):
                continue
            b, odd = _source_block(ijk, n, f, shape)
            if picks[s][b] < 0 and pick == 0:  # the first: listed at once, in point order
                o = min(s, 2)
                out[o, count[o]] = n
                count[o] += 1
            if picks[s][b] < 0 or (pick == 1 and odd == 1) or (pick == 2 and h < best[s][b]):
                picks[s][b] = n
                if pick == 2:
                    best[s][b] = h
    if pick != 0:  # the picks are final only now
        sets = [np.sort(p[p >= 0]).astype(np.int64) for p in picks]
        return sets[0], sets[1], np.sort(np.concatenate((sets[2], sets[3])))
    return out[0, : count[0]].copy(), out[1, : count[1]].copy(), out[2, : count[2]].copy()
