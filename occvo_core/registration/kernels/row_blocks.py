"""The map's rows in fixed blocks, each with the box of its rows' keys: a window reads only the blocks whose box
reaches it, not every row of the map. Rows are made a frame at a time, so a block holds one stretch of the drive and
most blocks lie far from any frame's window."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE

BLOCK_ROWS = 1024
EMPTY = np.iinfo(np.int64).max  # an empty block's lower bound (its upper is -EMPTY): it reaches no window


@njit(cache=CACHE, nogil=True)
def block_bounds(keys, n, first, lo, hi):
    """lo, hi = the smallest and largest key, per axis, of the rows < n of every block from `first` on (all rows,
    dropped ones too: a box only has to hold the rows a window may find)."""
    for b in range(first, lo.shape[0]):
        for a in range(3):
            lo[b, a] = EMPTY
            hi[b, a] = -EMPTY
        for r in range(b * BLOCK_ROWS, min(n, (b + 1) * BLOCK_ROWS)):
            for a in range(3):
                lo[b, a] = min(lo[b, a], keys[r, a])
                hi[b, a] = max(hi[b, a], keys[r, a])


@njit(cache=CACHE, nogil=True)
def grow_blocks(keys, rows, lo, hi):
    """Grow the boxes of the blocks of `rows` to hold those rows' keys (rows whose keys changed in place)."""
    for n in range(rows.shape[0]):
        r = rows[n]
        b = r // BLOCK_ROWS
        for a in range(3):
            lo[b, a] = min(lo[b, a], keys[r, a])
            hi[b, a] = max(hi[b, a], keys[r, a])


@njit(cache=CACHE, nogil=True, inline="always")
def block_reaches(lo, hi, b, lower, upper):
    """Whether block b's box meets the box of keys lower..upper."""
    return (
        lo[b, 0] <= upper[0]
        and lo[b, 1] <= upper[1]
        and lo[b, 2] <= upper[2]
        and hi[b, 0] >= lower[0]
        and hi[b, 1] >= lower[1]
        and hi[b, 2] >= lower[2]
    )
