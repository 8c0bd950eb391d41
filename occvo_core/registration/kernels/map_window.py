"""The map around a frame: its window of voxels, moved into the ego frame, pooled on a coarser grid."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occvo_core.registration.kernels import CACHE, CHUNKS
from occvo_core.registration.kernels.row_blocks import BLOCK_ROWS, block_reaches
from occvo_core.registration.kernels.turns import turn_before
from occvo_core.registration.voxel_pfilter import p_index as voxel_p_index


@njit(cache=CACHE, nogil=True, inline="always")
def _padded_cell(i, j, k, dims, pad):
    """Index of cell (i, j, k) of a box of dims in its grid with pad empty cells on every side."""
    return ((i + pad) * (dims[1] + 2 * pad) + j + pad) * (dims[2] + 2 * pad) + k + pad


@njit(cache=CACHE, nogil=True, parallel=True)
def empty_grid(n_cells):
    """A dense grid of n_cells, every cell empty (-1), filled in CHUNKS slices at once: the grid is megabytes."""
    grid = np.empty(n_cells, np.int32)
    for c in prange(CHUNKS):
        grid[n_cells * c // CHUNKS : n_cells * (c + 1) // CHUNKS] = -1
    return grid


@njit(cache=CACHE, nogil=True)
def key_bounds(keys, alive, n, block_lo, block_hi, lower, upper):
    """(min, max) key of the live rows < n with keys in [lower, upper]; min > max when there are none. Only the
    row blocks whose box (block_lo, block_hi: row_blocks) reaches the box are read."""
    lo = upper.copy() + 1
    hi = lower.copy() - 1
    for b in range((n + BLOCK_ROWS - 1) // BLOCK_ROWS):
        if not block_reaches(block_lo, block_hi, b, lower, upper):
            continue
        for r in range(b * BLOCK_ROWS, min(n, (b + 1) * BLOCK_ROWS)):
            if alive[r]:
                inside = True
                for a in range(3):
                    inside = inside and lower[a] <= keys[r, a] <= upper[a]
                if inside:
                    for a in range(3):
                        lo[a] = min(lo[a], keys[r, a])
                        hi[a] = max(hi[a], keys[r, a])
    return lo, hi


@njit(cache=CACHE, nogil=True, parallel=True)
def window_voxels(keys, alive, f, t0, pos, label, n, block_lo, block_hi, lower, upper, t):
    """Live rows < n with keys in [lower, upper], in row order, with copies of their positions and labels, their
    p-index f / max(t - t0, 1), and the dense grid of the box holding each one's window index (one pass, not five).
    Only the row blocks whose box (block_lo, block_hi: row_blocks) reaches the window are read row by row."""
    dims = upper - lower + 1
    grid = empty_grid(dims[0] * dims[1] * dims[2])
    inside = np.empty(n, np.bool_)
    counts = np.zeros(CHUNKS + 1, np.int64)
    for c in prange(CHUNKS):  # count each slice's rows in parallel
        r, end = n * c // CHUNKS, n * (c + 1) // CHUNKS
        while r < end:
            stop = min(end, (r // BLOCK_ROWS + 1) * BLOCK_ROWS)
            if not block_reaches(block_lo, block_hi, r // BLOCK_ROWS, lower, upper):
                inside[r:stop] = False
                r = stop
                continue
            for q in range(r, stop):
                i = keys[q, 0] - lower[0]
                j = keys[q, 1] - lower[1]
                k = keys[q, 2] - lower[2]
                inside[q] = alive[q] and 0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]
                if inside[q]:
                    counts[c + 1] += 1
            r = stop
    for c in range(CHUNKS):
        counts[c + 1] += counts[c]
    m = counts[CHUNKS]
    rows = np.empty(m, np.int64)
    for c in prange(CHUNKS):
        a = counts[c]
        for r in range(n * c // CHUNKS, n * (c + 1) // CHUNKS):
            if inside[r]:
                rows[a] = r
                a += 1
    out_pos = np.empty((m, 3))
    out_label = np.empty(m, np.uint8)
    p_index = np.empty(m)
    cell_of = np.empty(m, np.int64)
    for a in prange(m):
        r = rows[a]
        cell_of[a] = ((keys[r, 0] - lower[0]) * dims[1] + keys[r, 1] - lower[1]) * dims[2] + keys[r, 2] - lower[2]
        out_pos[a, 0] = pos[r, 0]
        out_pos[a, 1] = pos[r, 1]
        out_pos[a, 2] = pos[r, 2]
        out_label[a] = label[r]
        p_index[a] = voxel_p_index(f[r], t - t0[r])
    for a in range(m):  # in row order: a later row with the same key wins
        grid[cell_of[a]] = a
    return rows, out_pos, out_label, p_index, grid


@njit(cache=CACHE, nogil=True)
def clear_cells(grid, cells):
    """Empty (-1) the cells of grid that a build wrote (cells < 0: none), not the whole megabytes."""
    for c in cells:
        if c >= 0:
            grid[c] = -1


@njit(cache=CACHE, nogil=True, parallel=True)
def ego_points_into(idx, rows, map_pos, map_cov, rot, trans, origin, dims, voxel, pad, pos, cov, grid, cell_of):
    """Map voxels rows[idx] moved into the frame of the pose (rot, trans): positions R^T (p - t) into pos,
    covariances R^T C R into cov, and their cells in the box origin..origin + dims, with pad empty cells on every
    side, into grid (every cell empty on entry; of two voxels in one cell, the first in turn_before's order) and
    cell_of (each one's cell, -1 outside). The caller gives the arrays: reused ones spare a frame its page faults."""
    n = idx.shape[0]
    for a in prange(n):
        r = rows[idx[a]]
        d0 = map_pos[r, 0] - trans[0]
        d1 = map_pos[r, 1] - trans[1]
        d2 = map_pos[r, 2] - trans[2]
        for b in range(3):
            pos[a, b] = d0 * rot[0, b] + d1 * rot[1, b] + d2 * rot[2, b]
        for u in range(3):  # R^T C R
            t0 = rot[0, u] * map_cov[r, 0, 0] + rot[1, u] * map_cov[r, 1, 0] + rot[2, u] * map_cov[r, 2, 0]
            t1 = rot[0, u] * map_cov[r, 0, 1] + rot[1, u] * map_cov[r, 1, 1] + rot[2, u] * map_cov[r, 2, 1]
            t2 = rot[0, u] * map_cov[r, 0, 2] + rot[1, u] * map_cov[r, 1, 2] + rot[2, u] * map_cov[r, 2, 2]
            for v in range(3):
                cov[a, u, v] = t0 * rot[0, v] + t1 * rot[1, v] + t2 * rot[2, v]
        i = int(np.floor(pos[a, 0] / voxel)) - origin[0]
        j = int(np.floor(pos[a, 1] / voxel)) - origin[1]
        k = int(np.floor(pos[a, 2] / voxel)) - origin[2]
        inside = 0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]
        cell_of[a] = _padded_cell(i, j, k, dims, pad) if inside else -1
    for a in range(n):  # two voxels in one cell: turn_before's first wins (row order turns with the frames)
        c = cell_of[a]
        if c >= 0:
            b = grid[c]
            if b < 0 or turn_before(pos[a, 0], pos[a, 1], pos[a, 2], pos[b, 0], pos[b, 1], pos[b, 2]):
                grid[c] = a


def ego_points(idx, rows, map_pos, map_cov, rot, trans, origin, dims, voxel, pad):
    """ego_points_into on new arrays: (pos, cov, grid)."""
    n = len(idx)
    pos, cov = np.empty((n, 3)), np.empty((n, 3, 3))
    grid = empty_grid(int(np.prod(np.asarray(dims) + 2 * pad)))
    ego_points_into(
        idx, rows, map_pos, map_cov, rot, trans, origin, dims, voxel, pad, pos, cov, grid, np.empty(n, np.int64)
    )
    return pos, cov, grid


POOL_POS_STEP = 2.0**-32  # metres: the pooled sums' unit for positions (an ego box's sums stay under 2^53 of it)
POOL_COV_STEP = 2.0**-40  # the same for covariance entries (at most 1 here)


@njit(cache=CACHE, nogil=True, inline="always")
def _fixed(x, step):
    """x in whole units of step (a power of two): exact sums in any order, and rint(-x) = -rint(x), so a turned
    point's units are its turned units."""
    return np.int64(np.rint(x / step))


@njit(cache=CACHE, nogil=True)
def pool_voxels(pos, cov, labels, usable, weight, votes_in, voxel, origin, dims, n_classes, pad):
    """Weighted mean position and covariance and majority label of the usable points in each cell of a coarser grid.
    weight and votes_in (empty: one point, one vote of its label) carry a pooled map's counts, so pooling it again
    is pooling its voxels directly (to the sums' units). Returns pos, cov, labels, dense grid of the cells (with pad
    empty cells on every side), weights, votes.
    The sums are whole numbers of POOL_POS_STEP and POOL_COV_STEP: exact, so neither the points' order nor the
    number of threads nor a turn of the frame changes a bit, and the points are read once, in their order (a sort
    of each cell's points, scattered in memory, took three times as long)."""
    n_pts = pos.shape[0]
    grid = empty_grid((dims[0] + 2 * pad) * (dims[1] + 2 * pad) * (dims[2] + 2 * pad))
    slot = np.empty(n_pts, np.int64)
    n_out = 0
    for n in range(n_pts):  # cells numbered in order of first point
        slot[n] = -1
        if usable[n]:
            i = int(np.floor(pos[n, 0] / voxel)) - origin[0]
            j = int(np.floor(pos[n, 1] / voxel)) - origin[1]
            k = int(np.floor(pos[n, 2] / voxel)) - origin[2]
            if 0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]:
                c = _padded_cell(i, j, k, dims, pad)
                if grid[c] < 0:
                    grid[c] = n_out
                    n_out += 1
                slot[n] = grid[c]
    sums = np.zeros((n_out, 9), np.int64)  # x y z, then the covariance's upper triangle
    votes = np.zeros((n_out, n_classes), np.int32)
    count = np.zeros(n_out)
    weighted = weight.shape[0] > 0
    pooled_votes = votes_in.shape[0] > 0
    for n in range(n_pts):
        s = slot[n]
        if s < 0:
            continue
        w = np.int64(weight[n]) if weighted else np.int64(1)  # a pooled map's weights are voxel counts
        e = 3
        for a in range(3):
            sums[s, a] += w * _fixed(pos[n, a], POOL_POS_STEP)
            for b in range(a, 3):
                sums[s, e] += w * _fixed(cov[n, a, b], POOL_COV_STEP)
                e += 1
        if pooled_votes:
            for v in range(n_classes):
                votes[s, v] += votes_in[n, v]
        else:
            votes[s, labels[n]] += 1
        count[s] += w
    out_pos = np.empty((n_out, 3))
    out_cov = np.empty((n_out, 3, 3))
    out_lab = np.empty(n_out, np.uint8)
    for s in range(n_out):
        e = 3
        for a in range(3):
            out_pos[s, a] = sums[s, a] * POOL_POS_STEP / count[s]
            for b in range(a, 3):
                out_cov[s, a, b] = out_cov[s, b, a] = sums[s, e] * POOL_COV_STEP / count[s]
                e += 1
        best = 0
        for v in range(n_classes):
            if votes[s, v] > votes[s, best]:
                best = v
        out_lab[s] = best
    return out_pos, out_cov, out_lab, grid, count, votes
