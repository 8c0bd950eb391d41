"""Whole rows of the map: tiles paged out, rows moved by a loop closure, and arrays copied without the GIL (numpy's
copies of a big map's arrays hold it long enough to stall a worker's other threads)."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.covariance import rigid_motion
from occvo_core.registration.kernels.turns import turn_before


@njit(cache=CACHE, nogil=True)
def far_tile_rows(pos, alive, n, cx, cy, tile_m, radius):
    """Live rows < n, ascending, whose x-y tile (floor(xy / tile_m)) lies wholly farther than radius from (cx, cy):
    one pass, so the eviction check of a frame with nothing to evict costs no sort of the map."""
    out = np.empty(n, np.int64)
    m = 0
    r2 = radius * radius
    for r in range(n):
        if not alive[r]:
            continue
        lo_x = np.floor(pos[r, 0] / tile_m) * tile_m
        lo_y = np.floor(pos[r, 1] / tile_m) * tile_m
        dx = max(max(lo_x - cx, 0.0), cx - (lo_x + tile_m))
        dy = max(max(lo_y - cy, 0.0), cy - (lo_y + tile_m))
        if dx * dx + dy * dy > r2:
            out[m] = r
            m += 1
    return out[:m]


@njit(cache=CACHE, nogil=True)
def move_rows(pos, cov, keys, rows, rot, trans, group, voxel, box):
    """Map rows moved in place, each by the rotation and translation of its group (as rigid_motions), and their
    keys recomputed. Returns which moved more than a voxel; box (xmin, ymin, xmax, ymax) grows to hold them before
    and after. In place: a lap's rows would otherwise be gathered, moved and scattered in copies."""
    far = np.empty(rows.shape[0], np.bool_)
    c = np.empty((3, 3))
    for n in range(rows.shape[0]):
        r = rows[n]
        p0, p1, p2 = pos[r, 0], pos[r, 1], pos[r, 2]
        c[:, :] = cov[r]
        rigid_motion(rot, trans, group[n], p0, p1, p2, c, pos[r], cov[r])
        d0, d1, d2 = pos[r, 0] - p0, pos[r, 1] - p1, pos[r, 2] - p2
        far[n] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > voxel
        for a in range(3):
            keys[r, a] = np.int64(np.floor(pos[r, a] / voxel))
        box[0] = min(box[0], p0, pos[r, 0])
        box[1] = min(box[1], p1, pos[r, 1])
        box[2] = max(box[2], p0, pos[r, 0])
        box[3] = max(box[3], p1, pos[r, 1])
    return far


@njit(cache=CACHE, nogil=True)
def claim_cells(keys, pos, rows, grid, origin, dims):
    """Which moved rows may stay: those whose cell holds no voxel of the window grid and, of the moved rows in one
    cell, the first in turn_before's order (row order follows the order frames were turned in). Claimed cells are
    marked -2 in grid (an empty cell to nearest_in_window)."""
    keep = np.zeros(rows.shape[0], np.bool_)
    cells = np.empty(rows.shape[0], np.int64)
    for n in range(rows.shape[0]):
        r = rows[n]
        cell = ((keys[r, 0] - origin[0]) * dims[1] + keys[r, 1] - origin[1]) * dims[2] + keys[r, 2] - origin[2]
        cells[n] = cell
        held = grid[cell]
        if held == -1:
            grid[cell] = -3 - n  # claimed by moved row n, for now
        elif held <= -3:
            o = rows[-3 - held]
            if turn_before(pos[r, 0], pos[r, 1], pos[r, 2], pos[o, 0], pos[o, 1], pos[o, 2]):
                grid[cell] = -3 - n
    for n in range(rows.shape[0]):
        keep[n] = grid[cells[n]] == -3 - n
    for n in range(rows.shape[0]):
        if grid[cells[n]] <= -3:
            grid[cells[n]] = -2
    return keep


@njit(cache=CACHE, nogil=True)
def copy_row_bytes(dst, src, n):
    """dst[:n] = src[:n] for C-contiguous (rows, bytes per row) uint8 views."""
    d, s = dst.reshape(-1), src.reshape(-1)
    for k in range(n * src.shape[1]):
        d[k] = s[k]


@njit(cache=CACHE, nogil=True)
def gather_row_bytes(arr, keep):
    """arr[i] = arr[keep[i]] in place for increasing keep (keep[i] >= i: no row is read after it was written)."""
    w = arr.shape[1]
    for i in range(keep.size):
        k = keep[i]
        if k != i:
            for j in range(w):
                arr[i, j] = arr[k, j]


@njit(cache=CACHE, nogil=True)
def nonzero_entries(table):
    """The nonzero entries of a C-contiguous table as (flat index, value), in order, without the GIL: the map's class
    counts hold one or two classes of 18 a voxel, so their entries are a tenth of the table."""
    flat = table.reshape(-1)
    m = 0
    for i in range(flat.size):
        m += flat[i] != 0
    at = np.empty(m, np.uint32)
    values = np.empty(m, flat.dtype)
    m = 0
    for i in range(flat.size):
        if flat[i] != 0:
            at[m] = i
            values[m] = flat[i]
            m += 1
    return at, values
