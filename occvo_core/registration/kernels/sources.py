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


@njit(cache=CACHE, nogil=True)
def thin_sources(ijk, ground, shape, wide, coarse, fine, fine_ground, balanced=False):
    """The registration source sets, each one point of every factor^3 block of voxels (0: no set): one point per wide
    and per coarse block, and for fine one per fine block off the ground and per fine_ground block on it (the ground
    only holds z, roll and pitch). The point is the block's first in the points' order, which grid order makes its
    rear-most (lowest x); balanced: its last (front-most) in blocks of odd parity, so the picks lean neither way
    along the track. Indices ascending."""
    factors = (wide, coarse, fine, fine_ground)
    picks = []
    for f in factors:
        g = max(f, 1)
        picks.append(np.full(((shape[0] + g - 1) // g) * ((shape[1] + g - 1) // g) * ((shape[2] + g - 1) // g), -1, np.int32))
    out = np.empty((3, ijk.shape[0]), np.int64)
    count = np.zeros(3, np.int64)
    for n in range(ijk.shape[0]):
        for s in range(4):
            f = factors[s]
            if f == 0 or (s == 2 and ground[n]) or (s == 3 and not ground[n]):
                continue
            b, odd = _source_block(ijk, n, f, shape)
            if picks[s][b] < 0 and not balanced:  # the first: listed at once, in point order
                o = min(s, 2)
                out[o, count[o]] = n
                count[o] += 1
            if picks[s][b] < 0 or (balanced and odd == 1):
                picks[s][b] = n
    if balanced:  # the picks are final only now
        sets = [np.sort(p[p >= 0]).astype(np.int64) for p in picks]
        return sets[0], sets[1], np.sort(np.concatenate((sets[2], sets[3])))
    return out[0, :count[0]].copy(), out[1, :count[1]].copy(), out[2, :count[2]].copy()

