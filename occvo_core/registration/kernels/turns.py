"""Orders that a turn about z does not change: where two voxels tie (equal distance, one grid cell, one block),
the one kept must be the same physical voxel whichever way the frames were turned (by a multiple of 90 degrees,
which maps the 0.4 m lattice onto itself). Axis order and row order, which such a turn permutes, cannot decide."""

from __future__ import annotations

from numba import njit

from occvo_core.registration.kernels import CACHE


@njit(cache=CACHE, nogil=True, inline="always")
def turn_canonical_cell(i, j, shape):
    """The smallest x-y cell index among a grid cell and its turns about the grid's centre by 90, 180 and 270
    degrees (180 only on a grid that is not square): the same number for a cell and its turned copy."""
    ni, nj = shape[0], shape[1]
    best = i * nj + j
    best = min(best, (ni - 1 - i) * nj + (nj - 1 - j))
    if ni == nj:
        best = min(best, (nj - 1 - j) * nj + i)  # turned 90 degrees: (x, y) -> (-y, x)
        best = min(best, j * nj + (ni - 1 - i))
    return best


@njit(cache=CACHE, nogil=True, inline="always")
def canonical_xy(x, y):
    """The lexicographically smallest of (x, y) turned about the origin by 0, 90, 180 and 270 degrees (negation is
    exact, so a turned point gives the same pair bit for bit)."""
    bx, by = x, y
    for cx, cy in ((-y, x), (-x, -y), (y, -x)):
        if cx < bx or (cx == bx and cy < by):
            bx, by = cx, cy
    return bx, by


@njit(cache=CACHE, nogil=True, inline="always")
def turn_before(ax, ay, az, bx, by, bz):
    """Whether point a precedes point b in an order that turning both about the z axis through the origin by a
    multiple of 90 degrees keeps: canonical_xy, then z (a tie-break; distinct points that are not turned copies of
    each other never tie)."""
    pax, pay = canonical_xy(ax, ay)
    pbx, pby = canonical_xy(bx, by)
    return key_before(pax, pay, az, pbx, pby, bz)


@njit(cache=CACHE, nogil=True, inline="always")
def key_before(pax, pay, az, pbx, pby, bz):
    """turn_before on points whose (x, y) are canonical_xy already (a kernel that compares one point often keeps its
    canonical pair)."""
    if pax != pbx:
        return pax < pbx
    if pay != pby:
        return pay < pby
    return az < bz
