"""The map around a frame: its window of voxels, moved into the ego frame, pooled on a coarser grid."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occvo_core.registration.kernels import CACHE, CHUNKS
from occvo_core.registration.voxel_pfilter import p_index as voxel_p_index


@njit(cache=CACHE, nogil=True)
def key_bounds(keys, alive, n, lower, upper):
    """(min, max) key of the live rows < n with keys in [lower, upper]; min > max when there are none."""
    lo = upper.copy() + 1
    hi = lower.copy() - 1
    for r in range(n):
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
def window_voxels(keys, alive, f, t0, pos, label, n, lower, upper, t):
    """Live rows < n with keys in [lower, upper], in row order, with copies of their positions and labels, their
    p-index f / max(t - t0, 1), and the dense grid of the box holding each one's window index (one pass, not five)."""
    dims = upper - lower + 1
    n_cells = dims[0] * dims[1] * dims[2]
    grid = np.empty(n_cells, np.int32)
    for c in prange(CHUNKS):
        grid[n_cells * c // CHUNKS : n_cells * (c + 1) // CHUNKS] = -1
    inside = np.empty(n, np.bool_)
    counts = np.zeros(CHUNKS + 1, np.int64)
    for c in prange(CHUNKS):  # the scan of every row is the cost: count each slice's rows in parallel
        for r in range(n * c // CHUNKS, n * (c + 1) // CHUNKS):
            i = keys[r, 0] - lower[0]
            j = keys[r, 1] - lower[1]
            k = keys[r, 2] - lower[2]
            inside[r] = alive[r] and 0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]
            if inside[r]:
                counts[c + 1] += 1
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
    for a in prange(m):
        r = rows[a]
        out_pos[a, 0] = pos[r, 0]
        out_pos[a, 1] = pos[r, 1]
        out_pos[a, 2] = pos[r, 2]
        out_label[a] = label[r]
        p_index[a] = voxel_p_index(f[r], t - t0[r])
    for a in range(m):  # in row order: a later row with the same key wins
        r = rows[a]
        grid[((keys[r, 0] - lower[0]) * dims[1] + keys[r, 1] - lower[1]) * dims[2] + keys[r, 2] - lower[2]] = a
    return rows, out_pos, out_label, p_index, grid


@njit(cache=CACHE, nogil=True, parallel=True)
def ego_points(idx, rows, map_pos, map_cov, rot, trans, origin, dims, voxel):
    """Map voxels rows[idx] moved into the frame of the pose (rot, trans): positions R^T (p - t), covariances
    R^T C R, and the dense grid of their cells (a later voxel in the same cell wins)."""
    n = idx.shape[0]
    pos = np.empty((n, 3))
    cov = np.empty((n, 3, 3))
    grid = np.full(dims[0] * dims[1] * dims[2], -1, np.int32)
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
    for a in range(n):  # in order: a later voxel in the same cell wins
        i = int(np.floor(pos[a, 0] / voxel)) - origin[0]
        j = int(np.floor(pos[a, 1] / voxel)) - origin[1]
        k = int(np.floor(pos[a, 2] / voxel)) - origin[2]
        if 0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]:
            grid[(i * dims[1] + j) * dims[2] + k] = a
    return pos, cov, grid


@njit(cache=CACHE, nogil=True, parallel=True)
def pool_voxels(pos, cov, labels, usable, weight, votes_in, voxel, origin, dims, n_classes, parts):
    """Weighted mean position and covariance and majority label of the usable points in each cell of a coarser grid.
    weight and votes_in (empty: one point, one vote of its label) carry a pooled map's counts, so pooling it again
    equals pooling its voxels directly. Returns pos, cov, labels, dense grid of the cells, weights, votes."""
    n_cells = dims[0] * dims[1] * dims[2]
    grid = np.full(n_cells, -1, np.int32)
    slot = np.full(pos.shape[0], -1, np.int64)
    n_out = 0
    for n in range(pos.shape[0]):  # cells numbered in order of first point, serially
        if not usable[n]:
            continue
        i = int(np.floor(pos[n, 0] / voxel)) - origin[0]
        j = int(np.floor(pos[n, 1] / voxel)) - origin[1]
        k = int(np.floor(pos[n, 2] / voxel)) - origin[2]
        if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2]:
            continue
        cell = (i * dims[1] + j) * dims[2] + k
        if grid[cell] < 0:
            grid[cell] = n_out
            n_out += 1
        slot[n] = grid[cell]
    out_pos = np.zeros((n_out, 3))
    out_cov = np.zeros((n_out, 3, 3))
    votes = np.zeros((n_out, n_classes), np.int32)
    count = np.zeros(n_out)
    out_lab = np.empty(n_out, np.uint8)
    weighted = weight.shape[0] > 0
    pooled_votes = votes_in.shape[0] > 0
    # part c owns the cells s with (s // 64) % parts == c and adds their points in point order: the same sums on
    # any number of parts
    for c in prange(parts):
        for n in range(pos.shape[0]):
            s = slot[n]
            if s < 0 or (s >> 6) % parts != c:
                continue
            w = weight[n] if weighted else 1.0
            for a in range(3):
                out_pos[s, a] += w * pos[n, a]
                for b in range(3):
                    out_cov[s, a, b] += w * cov[n, a, b]
            if pooled_votes:
                for v in range(n_classes):
                    votes[s, v] += votes_in[n, v]
            else:
                votes[s, labels[n]] += 1
            count[s] += w
    for s in prange(n_out):
        for a in range(3):
            out_pos[s, a] /= count[s]
            for b in range(3):
                out_cov[s, a, b] /= count[s]
        best = 0
        for v in range(n_classes):
            if votes[s, v] > votes[s, best]:
                best = v
        out_lab[s] = best
    return out_pos, out_cov, out_lab, grid, count, votes
