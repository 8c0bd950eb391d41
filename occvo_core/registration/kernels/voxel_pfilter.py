"""Voxel pfilter: a frame merged into the map, sightings counted, the persistent voxels served."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.nearest import bucket_order
from occvo_core.registration.kernels.turns import turn_before
from occvo_core.registration.voxel_pfilter import p_index


@njit(cache=CACHE, nogil=True, inline="always")
def _grow_box(box, x, y):
    box[0] = min(box[0], x)
    box[1] = min(box[1], y)
    box[2] = max(box[2], x)
    box[3] = max(box[3], y)


@njit(cache=CACHE, nogil=True)
def voxel_keys(points, voxel):
    """Voxel key floor(p / voxel) of each point, and the keys' (min, max) per axis (min > max for no points): one
    pass where numpy takes five."""
    n = points.shape[0]
    keys = np.empty((n, 3), np.int64)
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)
    for i in range(n):
        for a in range(3):
            k = np.int64(np.floor(points[i, a] / voxel))
            keys[i, a] = k
            lo[a] = min(lo[a], k)
            hi[a] = max(hi[a], k)
    return keys, lo, hi


@njit(cache=CACHE, nogil=True)
def _turn_before_rows(pos, a, b):
    """turn_before of map points a and b, asked only on an exact tie of distances (rare): a call of its own here,
    where nearest.py's _nearer, inlined whole into this loop, left it about a fifth slower (measured)."""
    return turn_before(pos[a, 0], pos[a, 1], pos[a, 2], pos[b, 0], pos[b, 1], pos[b, 2])


@njit(cache=CACHE, nogil=True)
def _nearest_around(q, ci, cj, ck, map_pos, grid, dims, alive):
    """nearest_in_window(q, ..., radius 1, alive) for a point whose own cell (ci, cj, ck) holds no live voxel: the
    27 cells around it in the same order, with the same tie-break, so the same (index or -1, squared distance)."""
    best = -1
    best_d2 = np.inf
    for i in range(max(ci - 1, 0), min(ci + 2, dims[0])):
        for j in range(max(cj - 1, 0), min(cj + 2, dims[1])):
            base = (i * dims[1] + j) * dims[2]
            for k in range(max(ck - 1, 0), min(ck + 2, dims[2])):
                m = grid[base + k]
                if m >= 0 and alive[m]:
                    d0 = map_pos[m, 0] - q[0]
                    d1 = map_pos[m, 1] - q[1]
                    d2 = map_pos[m, 2] - q[2]
                    d = d0 * d0 + d1 * d1 + d2 * d2
                    if d < best_d2 or (d == best_d2 and best >= 0 and _turn_before_rows(map_pos, m, best)):
                        best, best_d2 = m, d
    return best, best_d2


@njit(cache=CACHE, nogil=True, inline="always")
def _observe(seen, map_pos, m, x, y, z, r2):
    """seen[m] |= map point m (a grid entry: < 0 is no point) lies within sqrt(r2) of (x, y, z), without a branch:
    which cells hold a point near is no pattern a branch predictor learns."""
    valid = m >= 0
    m = m if valid else 0
    d0 = map_pos[m, 0] - x
    d1 = map_pos[m, 1] - y
    d2 = map_pos[m, 2] - z
    seen[m] |= valid & (d0 * d0 + d1 * d1 + d2 * d2 <= r2)


@njit(cache=CACHE, nogil=True, inline="always")
def _observe_around(hit, p, ci, cj, ck, map_pos, grid, dims, radius_m):
    """_observe over the 27 cells around cell (ci, cj, ck) of the window's grid, for point p."""
    x, y, z, r2 = p[0], p[1], p[2], radius_m * radius_m
    if 1 <= ci < dims[0] - 1 and 1 <= cj < dims[1] - 1 and 1 <= ck < dims[2] - 1:
        for i in range(ci - 1, ci + 2):
            for j in range(cj - 1, cj + 2):
                cell = (i * dims[1] + j) * dims[2] + ck
                _observe(hit, map_pos, grid[cell - 1], x, y, z, r2)
                _observe(hit, map_pos, grid[cell], x, y, z, r2)
                _observe(hit, map_pos, grid[cell + 1], x, y, z, r2)
    else:  # at the window's faces
        for i in range(max(ci - 1, 0), min(ci + 2, dims[0])):
            for j in range(max(cj - 1, 0), min(cj + 2, dims[1])):
                base = (i * dims[1] + j) * dims[2]
                for k in range(max(ck - 1, 0), min(ck + 2, dims[2])):
                    _observe(hit, map_pos, grid[base + k], x, y, z, r2)


@njit(cache=CACHE, nogil=True, parallel=True)
def assign_voxels(
    points, keys, map_pos, grid, origin, dims, merge_radius, map_rows, alive, n_map, observe_radius, parts
):
    """Map row of each frame point: the live map voxel holding it; else the nearest live map point within
    merge_radius (so a surface straddling a voxel boundary stays one voxel across frames and its p-index measures
    persistence, not aliasing), unless another point in its cell has none near; else a new row, numbered from n_map
    on, for its voxel. With observe_radius > 0, also observe_points' sightings, read while the grid is at hand.
    Returns (rows, first point of each new row, sightings). The grid is used up: new rows are written into it."""
    n_pts = keys.shape[0]
    out = np.empty(n_pts, np.int64)
    near = np.empty(n_pts, np.int64)
    cells = np.empty(n_pts, np.int64)
    r2 = merge_radius * merge_radius
    observe = observe_radius > 0 and map_rows.shape[0] > 0
    seen = np.zeros((parts, map_rows.shape[0] if observe else 0), np.uint8)
    # lookups in the map's own voxels, a slice of the points a part (new rows never take part in them) ...
    for c in prange(parts):
        for n in range(n_pts * c // parts, n_pts * (c + 1) // parts):
            ci, cj, ck = keys[n, 0] - origin[0], keys[n, 1] - origin[1], keys[n, 2] - origin[2]
            cell = (ci * dims[1] + cj) * dims[2] + ck
            cells[n] = cell
            out[n] = near[n] = -1
            local = grid[cell]
            if local >= 0 and alive[local]:
                out[n] = map_rows[local]
            elif r2 > 0.0:
                m, d2 = _nearest_around(points[n], ci, cj, ck, map_pos, grid, dims, alive)
                if m >= 0 and d2 <= r2:
                    near[n] = map_rows[m]
            if observe:
                _observe_around(seen[c], points[n], ci, cj, ck, map_pos, grid, dims, observe_radius)
    # ... then a new row for each empty cell holding a point with no map point near; every point of such a cell
    # joins it (whatever the points' order, which turns with the frame), the others their nearest map point
    first_key = np.empty(n_pts, np.int64)
    n_new = 0
    for n in range(n_pts):
        if out[n] < 0 and near[n] < 0 and grid[cells[n]] > -3:
            first_key[n_new] = n
            grid[cells[n]] = -3 - n_new
            n_new += 1
    for n in range(n_pts):
        if out[n] >= 0:
            continue
        local = grid[cells[n]]
        out[n] = n_map + (-3 - local) if local <= -3 else near[n]
    return out, first_key[:n_new], seen


@njit(cache=CACHE, nogil=True, parallel=True)
def merge_points(rows, pw, cw, labels, t, pos, cov, counts, label, t0, f, last, wacc, use_p_index, changed, parts):
    """Voxel PFilter merge, in place: each touched voxel becomes the weighted mean of its old point
    (weight f * p-index, or f without the filter) and the frame's points in it (weight 1 each).
    changed (xmin, ymin, xmax, ymax) grows to hold every touched voxel before and after."""
    # part c (one a thread) owns the blocks of 64 rows b with b % parts == c and adds their points in point order, so
    # every voxel sums the same numbers in the same order for any number of parts (no shared cache lines); the
    # points taken a block at a time keep a frame's scattered rows from missing the cache at every point
    n_blocks = (pos.shape[0] + 63) >> 6
    order, start = bucket_order(rows >> 6, n_blocks)  # the points by block, in point order within one
    boxes = np.empty((parts, 4))
    for c in prange(parts):
        box = boxes[c]
        box[0] = box[1] = np.inf
        box[2] = box[3] = -np.inf
        for b in range(c, n_blocks, parts):
            for q in range(start[b], start[b + 1]):
                n = order[q]
                r = rows[n]
                if last[r] != t:  # first point of this frame in voxel r
                    if f[r] > 0:
                        _grow_box(box, pos[r, 0], pos[r, 1])
                        w = f[r] * p_index(f[r], t - t0[r]) if use_p_index else float(f[r])
                    else:
                        w = 0.0
                    for a in range(3):
                        pos[r, a] *= w
                        for e in range(3):
                            cov[r, a, e] *= w
                    wacc[r] = w
                    f[r] += 1
                    last[r] = t
                for a in range(3):
                    pos[r, a] += pw[n, a]
                    for e in range(3):
                        cov[r, a, e] += cw[n, a, e]
                wacc[r] += 1.0
                counts[r, labels[n]] += 1
            for q in range(start[b], start[b + 1]):
                r = rows[order[q]]
                if wacc[r] <= 0.0:
                    continue
                inv = 1.0 / wacc[r]
                for a in range(3):
                    pos[r, a] *= inv
                    for e in range(3):
                        cov[r, a, e] *= inv
                wacc[r] = 0.0
                _grow_box(box, pos[r, 0], pos[r, 1])
                best = 0
                for k in range(counts.shape[1]):
                    if counts[r, k] > counts[r, best]:
                        best = k
                label[r] = best
    for c in range(parts):
        if boxes[c, 0] <= boxes[c, 2]:  # this part touched a voxel
            _grow_box(changed, boxes[c, 0], boxes[c, 1])
            _grow_box(changed, boxes[c, 2], boxes[c, 3])


@njit(cache=CACHE, nogil=True, parallel=True)
def observe_points(points, keys, map_pos, grid, origin, dims, radius_m, n_win, parts):
    """Sightings for count_observed: which window voxels lie within radius_m of a frame point (keys: the points'
    voxels), a row of them a part. A grid entry < 0 is no voxel (assign_voxels' new rows among them)."""
    # part c (one a thread) marks the voxels near its slice of the points in a row of its own, so the unconditional
    # writes never race; a voxel is seen when any part saw it, whatever the number of parts
    seen = np.zeros((parts, n_win), np.uint8)
    n_pts = points.shape[0]
    if n_win == 0:
        return seen
    for c in prange(parts):
        for n in range(n_pts * c // parts, n_pts * (c + 1) // parts):
            ci, cj, ck = keys[n, 0] - origin[0], keys[n, 1] - origin[1], keys[n, 2] - origin[2]
            _observe_around(seen[c], points[n], ci, cj, ck, map_pos, grid, dims, radius_m)
    return seen


@njit(cache=CACHE, nogil=True, parallel=True)
def count_observed(seen, map_pos, map_rows, alive, f, last, in_window, t, changed, parts):
    """Count as seen at frame t every live window voxel a part saw (seen: observe_points' or assign_voxels'), once a
    frame: a surface that straddles a voxel boundary falls in either voxel from frame to frame, and must not lose
    its p-index for it. changed grows to hold the voxels counted. Then mark_in_window, in the same pass."""
    n_win = seen.shape[1]
    # window rows are distinct map rows: slices count theirs apart, and a box's min and max take any order
    boxes = np.empty((parts, 4))
    for c in prange(parts):
        box = boxes[c]
        box[0] = box[1] = np.inf
        box[2] = box[3] = -np.inf
        for m in range(n_win * c // parts, n_win * (c + 1) // parts):
            near = 0
            for p in range(seen.shape[0]):
                near |= seen[p, m]
            row = map_rows[m]
            if near and alive[m] and last[row] != t:  # not merged into (nor counted) at t already
                _grow_box(box, map_pos[m, 0], map_pos[m, 1])
                f[row] += 1
                last[row] = t
            if last[row] == t:
                in_window[row] = t
    for c in range(parts):
        if boxes[c, 0] <= boxes[c, 2]:
            _grow_box(changed, boxes[c, 0], boxes[c, 1])
            _grow_box(changed, boxes[c, 2], boxes[c, 3])


@njit(cache=CACHE, nogil=True)
def window_rows_state(rows, alive, returning, last):
    """One pass over a merge's window rows: whether each is alive, and the rows back in view after frames away
    (returning) with their last sightings."""
    n = rows.shape[0]
    alive_out = np.empty(n, np.bool_)
    back = np.empty(n, np.int64)
    n_back = 0
    for a in range(n):
        r = rows[a]
        alive_out[a] = alive[r]
        if returning[r]:
            back[n_back] = r
            n_back += 1
    back = back[:n_back].copy()
    back_last = np.empty(n_back, last.dtype)
    for b in range(n_back):
        back_last[b] = last[back[b]]
    return alive_out, back, back_last


@njit(cache=CACHE, nogil=True)
def mark_in_window(rows, last, in_window, t):
    """in_window = t for the window rows seen at frame t."""
    for a in range(rows.shape[0]):
        r = rows[a]
        if last[r] == t:
            in_window[r] = t


@njit(cache=CACHE, nogil=True)
def window_gaps(rows, in_window, t):
    """For VoxelPFilterMap.enter(): frames each window row spent outside the registration windows before frame t
    (0 for none), and which of them (window indices) were away: one pass where numpy takes five."""
    n = rows.shape[0]
    away = np.empty(n, in_window.dtype)  # the p-index of a row back takes the dtype the warm-up compiled
    back = np.empty(n, np.int64)
    n_back = 0
    for a in range(n):
        gap = (t - 1) - np.int64(in_window[rows[a]])
        away[a] = max(gap, 0)
        if gap > 0:
            back[n_back] = a
            n_back += 1
    return away, back[:n_back].copy()


@njit(cache=CACHE, nogil=True)
def record_window(rows, away, alive, t0, last, returning, in_window, t):
    """VoxelPFilterMap.entered() on the live rows: t0 and the last sighting move on by the frames away, returning
    marks those that were away, and in_window says frame t's window held them."""
    for n in range(rows.shape[0]):
        r = rows[n]
        if alive[r]:
            t0[r] += away[n]
            last[r] += away[n]
            if away[n] > 0:
                returning[r] = True
            in_window[r] = t


@njit(cache=CACHE, nogil=True)
def persistent_in_tiles(pos, alive, f, last, t0, between, n, threshold, use_p_index, lo, hi, tile_m):
    """Rows < n of VoxelPFilterMap.persistent() whose x-y tile floor(pos / tile_m) lies in lo..hi, in row order."""
    out = np.empty(n, np.int64)
    n_out = 0
    for r in range(n):
        if not alive[r]:
            continue
        ix = np.floor(pos[r, 0] / tile_m)
        iy = np.floor(pos[r, 1] / tile_m)
        if ix < lo[0] or ix > hi[0] or iy < lo[1] or iy > hi[1]:
            continue
        if use_p_index and not p_index(f[r], last[r] - t0[r] + 1 - between[r]) > threshold:
            continue
        out[n_out] = r
        n_out += 1
    return out[:n_out]
