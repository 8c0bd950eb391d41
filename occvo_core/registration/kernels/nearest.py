"""Nearest-neighbour search on dense voxel grids (no trees: every map lives on a fixed grid)."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.turns import turn_before


@njit(cache=CACHE, nogil=True, inline="always")
def _nearer(q, map_pos, m, usable, best, best_d2):
    """(best, squared distance) after looking at grid entry m: m when it is a usable point nearer; on a tie the one
    first in turn_before's order, not the one seen first (the order cells are read in turns with the frame)."""
    if m >= 0 and usable[m]:
        d0 = map_pos[m, 0] - q[0]
        d1 = map_pos[m, 1] - q[1]
        d2 = map_pos[m, 2] - q[2]
        d = d0 * d0 + d1 * d1 + d2 * d2
        if d < best_d2 or (
            d == best_d2
            and best >= 0
            and turn_before(
                map_pos[m, 0], map_pos[m, 1], map_pos[m, 2], map_pos[best, 0], map_pos[best, 1], map_pos[best, 2]
            )
        ):
            return m, d
    return best, best_d2


@njit(cache=CACHE, nogil=True, inline="always")
def _beyond_best(q, ci, cj, ck, origin, r, voxel, best_d2):
    """Whether every point outside the cube of rings 0..r around cell (ci, cj, ck) lies farther than the best (strictly:
    one as near would be a tie, which turn_before decides)."""
    gap = np.inf
    for a, c in ((0, ci), (1, cj), (2, ck)):
        gap = min(gap, q[a] - (c + origin[a] - r) * voxel, (c + origin[a] + r + 1) * voxel - q[a])
    return best_d2 < gap * gap


@njit(cache=CACHE, nogil=True)
def nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius, usable):
    """Nearest usable map point to q within `radius` voxel rings: (index or -1, squared distance).

    Rings are searched outwards and the search stops as soon as the best distance is below the distance to the
    faces of the cube searched so far."""
    ci = int(np.floor(q[0] / voxel)) - origin[0]
    cj = int(np.floor(q[1] / voxel)) - origin[1]
    ck = int(np.floor(q[2] / voxel)) - origin[2]
    best = -1
    best_d2 = np.inf
    for r in range(radius + 1):
        for di in range(-r, r + 1):
            i = ci + di
            if i < 0 or i >= dims[0]:
                continue
            edge_i = di == -r or di == r
            for dj in range(-r, r + 1):
                j = cj + dj
                if j < 0 or j >= dims[1]:
                    continue
                edge_ij = edge_i or dj == -r or dj == r
                base = (i * dims[1] + j) * dims[2]
                step = 1 if edge_ij else 2 * r  # inside the ring only the two z faces are new
                dk = -r
                while dk <= r:
                    k = ck + dk
                    if 0 <= k < dims[2]:
                        best, best_d2 = _nearer(q, map_pos, grid[base + k], usable, best, best_d2)
                    dk += step if step > 0 else 1
        # every unsearched point lies outside the searched cube: stop once the best is nearer than its faces
        if best >= 0 and _beyond_best(q, ci, cj, ck, origin, r, voxel, best_d2):
            break
    return best, best_d2


@njit(cache=CACHE, nogil=True, inline="always")
def _axis_gap(o, lo, voxel):
    """Distance along one axis from a query to the cell o cells away (lo: the query to its own cell's lower face),
    less a nanometre, so that rounding never makes it more than the distance of a point in that cell."""
    if o == 0:
        return 0.0
    return max(0.0, (abs(o) - 1) * voxel + ((voxel - lo) if o > 0 else lo) - 1e-9)


@njit(cache=CACHE, nogil=True, inline="always")
def square_gaps(q, ci, cj, ck, origin, voxel, radius, gaps):
    """gaps[a, o + radius]: the squared gap along axis a from q to the cells o away from q's cell (ci, cj, ck)."""
    lo0, lo1, lo2 = q[0] - (ci + origin[0]) * voxel, q[1] - (cj + origin[1]) * voxel, q[2] - (ck + origin[2]) * voxel
    for o in range(-radius, radius + 1):
        gaps[0, o + radius] = _axis_gap(o, lo0, voxel) ** 2
        gaps[1, o + radius] = _axis_gap(o, lo1, voxel) ** 2
        gaps[2, o + radius] = _axis_gap(o, lo2, voxel) ** 2


@njit(cache=CACHE, nogil=True, inline="always")
def nearest_within_gaps(q, map_pos, grid, origin, dims, voxel, radius, usable, max_d2, gaps):
    """nearest_in_window for a caller that keeps only a point within max_d2: the same point whenever that one is
    within it (a farther one or none otherwise). Beyond the query's own cell it reads only the cells that can hold a
    point nearer than the best so far and within max_d2, row by row in nearest_in_window's order (whole rows out of
    reach skipped). A query at least `radius` cells from the grid's edges needs no bounds check a cell (an EgoMap's
    grid has that many empty cells on every side). gaps: (3, 2 radius + 1) scratch for the squared gaps to the
    cells along each axis, taken once a query rather than once a cell."""
    ci = int(np.floor(q[0] / voxel)) - origin[0]
    cj = int(np.floor(q[1] / voxel)) - origin[1]
    ck = int(np.floor(q[2] / voxel)) - origin[2]
    if min(ci, cj, ck) < radius or ci >= dims[0] - radius or cj >= dims[1] - radius or ck >= dims[2] - radius:
        return nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius, usable)
    c = (ci * dims[1] + cj) * dims[2] + ck
    best, best_d2 = _nearer(q, map_pos, grid[c], usable, -1, np.inf)
    if best >= 0 and _beyond_best(q, ci, cj, ck, origin, 0, voxel, best_d2):
        return best, best_d2
    square_gaps(q, ci, cj, ck, origin, voxel, radius, gaps)
    for r in range(1, radius + 1):
        for di in range(-r, r + 1):
            gi = gaps[0, di + radius]
            if gi >= best_d2 or gi > max_d2:
                continue
            edge_i = di == -r or di == r
            for dj in range(-r, r + 1):
                gij = gi + gaps[1, dj + radius]
                if gij >= best_d2 or gij > max_d2:
                    continue
                base = c + (di * dims[1] + dj) * dims[2]
                step = 1 if edge_i or dj == -r or dj == r else 2 * r  # inside the ring: the z faces
                for dk in range(-r, r + 1, step):
                    d2 = gij + gaps[2, dk + radius]
                    if d2 < best_d2 and d2 <= max_d2:
                        m = grid[base + dk]
                        if m >= 0:
                            best, best_d2 = _nearer(q, map_pos, m, usable, best, best_d2)
        if best >= 0 and _beyond_best(q, ci, cj, ck, origin, r, voxel, best_d2):
            break
    return best, best_d2


@njit(cache=CACHE, nogil=True)
def nearest_within(q, map_pos, grid, origin, dims, voxel, radius, usable, max_d2):
    """nearest_within_gaps with scratch of its own (a caller with many queries keeps one)."""
    gaps = np.empty((3, 2 * radius + 1))
    return nearest_within_gaps(q, map_pos, grid, origin, dims, voxel, radius, usable, max_d2, gaps)


@njit(cache=CACHE, nogil=True)
def nearest_distances(queries, map_pos, grid, origin, dims, voxel, radius, usable):
    out = np.empty(queries.shape[0])
    idx = np.empty(queries.shape[0], np.int64)
    for n in range(queries.shape[0]):
        m, d2 = nearest_in_window(queries[n], map_pos, grid, origin, dims, voxel, radius, usable)
        idx[n] = m
        out[n] = np.sqrt(d2) if m >= 0 else np.inf
    return out, idx


@njit(cache=CACHE, nogil=True)
def bucket_order(keys, n_buckets):
    """(order, start): the items by key, bucket b's being order[start[b]:start[b + 1]] in item order (a stable
    counting sort)."""
    start = np.zeros(n_buckets + 1, np.int64)
    for i in range(keys.shape[0]):
        start[keys[i] + 1] += 1
    for b in range(n_buckets):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    order = np.empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    return order, start


@njit(cache=CACHE, nogil=True)
def cell_sort(points, cell):
    """Points bucketed in cubes of side `cell` from their lowest corner (counting sort): (lo, dims, start, order),
    the points of cube c being order[start[c]:start[c + 1]]."""
    n = points.shape[0]
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = points[:, a].min()
        dims[a] = int((points[:, a].max() - lo[a]) / cell) + 1
    cell_of = np.empty(n, np.int64)
    for i in range(n):
        cell_of[i] = (int((points[i, 0] - lo[0]) / cell) * dims[1] + int((points[i, 1] - lo[1]) / cell)) * dims[
            2
        ] + int((points[i, 2] - lo[2]) / cell)
    order, start = bucket_order(cell_of, dims[0] * dims[1] * dims[2])
    return lo, dims, start, order


@njit(cache=CACHE, nogil=True, inline="always")
def near_one(x0, x1, x2, points, lo, dims, start, order, radius):
    """Whether some point lies within radius of (x0, x1, x2) (distance not above it), in cell_sort's grid of
    radius-sized cells over the points: the 27 cells around the query's."""
    c0 = int(np.floor((x0 - lo[0]) / radius))
    c1 = int(np.floor((x1 - lo[1]) / radius))
    c2 = int(np.floor((x2 - lo[2]) / radius))
    for i in range(max(c0 - 1, 0), min(c0 + 2, dims[0])):
        for j in range(max(c1 - 1, 0), min(c1 + 2, dims[1])):
            base = (i * dims[1] + j) * dims[2]
            for cell in range(base + max(c2 - 1, 0), base + min(c2 + 2, dims[2])):
                for s in range(start[cell], start[cell + 1]):
                    p = order[s]
                    d0 = x0 - points[p, 0]
                    d1 = x1 - points[p, 1]
                    d2 = x2 - points[p, 2]
                    if not np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > radius:
                        return True
    return False


@njit(cache=CACHE, nogil=True)
def near_any(queries, points, radius):
    """For each query, whether some point lies within radius (distance not above it), through a grid of
    radius-sized cells over the points (counting sort)."""
    out = np.zeros(queries.shape[0], np.bool_)
    if points.shape[0] == 0:
        return out
    lo, dims, start, order = cell_sort(points, radius)
    for q in range(queries.shape[0]):
        out[q] = near_one(queries[q, 0], queries[q, 1], queries[q, 2], points, lo, dims, start, order, radius)
    return out
