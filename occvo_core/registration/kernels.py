"""Compiled inner loops. Every frame lives on a 0.4 m grid, so neighbour search is a dense-array lookup, not a tree."""

from __future__ import annotations

import numpy as np
from numba import njit

_CACHE = True


@njit(cache=_CACHE, nogil=True)
def dense_index(ijk, shape):
    """Flat dense grid holding each point's row index (-1 = empty); points outside the grid are left out."""
    grid = np.full(shape[0] * shape[1] * shape[2], -1, np.int32)
    for n in range(ijk.shape[0]):
        i, j, k = ijk[n, 0], ijk[n, 1], ijk[n, 2]
        if 0 <= i < shape[0] and 0 <= j < shape[1] and 0 <= k < shape[2]:
            grid[(i * shape[1] + j) * shape[2] + k] = n
    return grid


@njit(cache=_CACHE, nogil=True)
def surface_mask(ijk, grid, shape):
    """True for voxels with an empty face neighbour. Interior voxels of solid objects repeat every voxel, which
    gives nearest-neighbour ICP a false minimum at every grid step, and have no surface normal."""
    out = np.ones(ijk.shape[0], np.bool_)
    for n in range(ijk.shape[0]):
        i, j, k = ijk[n, 0], ijk[n, 1], ijk[n, 2]
        if i <= 0 or j <= 0 or k <= 0 or i >= shape[0] - 1 or j >= shape[1] - 1 or k >= shape[2] - 1:
            continue
        s1, s2 = shape[1] * shape[2], shape[2]
        c = (i * shape[1] + j) * shape[2] + k
        if grid[c - s1] >= 0 and grid[c + s1] >= 0 and grid[c - s2] >= 0 and grid[c + s2] >= 0 and grid[c - 1] >= 0 and grid[c + 1] >= 0:
            out[n] = False
    return out


@njit(cache=_CACHE, nogil=True, inline="always")
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (closed form, no allocation)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    if p < 1e-12:
        return 0.0, 0.0, 1.0  # isotropic: no preferred normal
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2.0
    r = min(1.0, max(-1.0, r))
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)  # the smallest root
    # rows of (A - lam I); their cross products are parallel to the eigenvector
    r0x, r0y, r0z = a00 - lam, a01, a02
    r1x, r1y, r1z = a01, a11 - lam, a12
    r2x, r2y, r2z = a02, a12, a22 - lam
    c0x, c0y, c0z = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
    c1x, c1y, c1z = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
    c2x, c2y, c2z = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
    n0, n1, n2 = c0x * c0x + c0y * c0y + c0z * c0z, c1x * c1x + c1y * c1y + c1z * c1z, c2x * c2x + c2y * c2y + c2z * c2z
    if n0 >= n1 and n0 >= n2 and n0 > 1e-24:
        s = 1.0 / np.sqrt(n0)
        return c0x * s, c0y * s, c0z * s
    if n1 >= n2 and n1 > 1e-24:
        s = 1.0 / np.sqrt(n1)
        return c1x * s, c1y * s, c1z * s
    if n2 > 1e-24:
        s = 1.0 / np.sqrt(n2)
        return c2x * s, c2y * s, c2z * s
    return 0.0, 0.0, 1.0  # two smallest eigenvalues equal (a line): any normal across it will do


@njit(cache=_CACHE, nogil=True)
def plane_covariances(points, ijk, grid, shape, radius, epsilon):
    """GICP covariances (Segal et al.): the neighbourhood's plane, as eps along its normal and 1 across it."""
    n_pts = points.shape[0]
    covs = np.empty((n_pts, 3, 3))
    for n in range(n_pts):
        sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
        cnt = 0
        for di in range(-radius, radius + 1):
            i = ijk[n, 0] + di
            if i < 0 or i >= shape[0]:
                continue
            for dj in range(-radius, radius + 1):
                j = ijk[n, 1] + dj
                if j < 0 or j >= shape[1]:
                    continue
                for dk in range(-radius, radius + 1):
                    k = ijk[n, 2] + dk
                    if k < 0 or k >= shape[2]:
                        continue
                    m = grid[(i * shape[1] + j) * shape[2] + k]
                    if m < 0:
                        continue
                    x, y, z = points[m, 0], points[m, 1], points[m, 2]
                    cnt += 1
                    sx += x
                    sy += y
                    sz += z
                    sxx += x * x
                    sxy += x * y
                    sxz += x * z
                    syy += y * y
                    syz += y * z
                    szz += z * z
        if cnt < 3:  # too few neighbours for a surface: isotropic
            for a in range(3):
                for b in range(3):
                    covs[n, a, b] = 1.0 if a == b else 0.0
            continue
        mx, my, mz = sx / cnt, sy / cnt, sz / cnt
        nx, ny, nz = _smallest_eigenvector(sxx / cnt - mx * mx, sxy / cnt - mx * my, sxz / cnt - mx * mz,
                                           syy / cnt - my * my, syz / cnt - my * mz, szz / cnt - mz * mz)
        nv = (nx, ny, nz)
        for a in range(3):
            for b in range(3):
                covs[n, a, b] = (1.0 if a == b else 0.0) - (1.0 - epsilon) * nv[a] * nv[b]
    return covs


@njit(cache=_CACHE, nogil=True)
def first_per_block(ijk, factor, shape):
    """Downsampling on the grid: index of the first point in each factor^3 block of voxels."""
    bshape = ((shape[0] + factor - 1) // factor, (shape[1] + factor - 1) // factor, (shape[2] + factor - 1) // factor)
    seen = np.zeros(bshape[0] * bshape[1] * bshape[2], np.bool_)
    keep = np.empty(ijk.shape[0], np.int64)
    n_keep = 0
    for n in range(ijk.shape[0]):
        b = ((ijk[n, 0] // factor) * bshape[1] + ijk[n, 1] // factor) * bshape[2] + ijk[n, 2] // factor
        if not seen[b]:
            seen[b] = True
            keep[n_keep] = n
            n_keep += 1
    return keep[:n_keep]


@njit(cache=_CACHE, nogil=True)
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
                        m = grid[base + k]
                        if m >= 0 and usable[m]:
                            d0 = map_pos[m, 0] - q[0]
                            d1 = map_pos[m, 1] - q[1]
                            d2 = map_pos[m, 2] - q[2]
                            d = d0 * d0 + d1 * d1 + d2 * d2
                            if d < best_d2:
                                best_d2 = d
                                best = m
                    dk += step if step > 0 else 1
        if best >= 0:
            # every unsearched point lies outside the searched cube: stop once the best is nearer than its faces
            gap = np.inf
            for a, c in ((0, ci), (1, cj), (2, ck)):
                lo_face = (c + origin[a] - r) * voxel
                hi_face = (c + origin[a] + r + 1) * voxel
                gap = min(gap, q[a] - lo_face, hi_face - q[a])
            if best_d2 <= gap * gap:
                break
    return best, best_d2


@njit(cache=_CACHE, nogil=True)
def _inv3_sym(c):
    """Inverse of a symmetric positive-definite 3x3 matrix by cofactors (no LAPACK call per pair)."""
    a, b, cc = c[0, 0], c[0, 1], c[0, 2]
    d, e, f = c[1, 1], c[1, 2], c[2, 2]
    A = d * f - e * e
    B = cc * e - b * f
    C = b * e - cc * d
    det = a * A + b * B + cc * C
    out = np.empty((3, 3))
    inv_det = 1.0 / det
    out[0, 0] = A * inv_det
    out[0, 1] = out[1, 0] = B * inv_det
    out[0, 2] = out[2, 0] = C * inv_det
    out[1, 1] = (a * f - cc * cc) * inv_det
    out[1, 2] = out[2, 1] = (b * cc - a * e) * inv_det
    out[2, 2] = (a * d - b * b) * inv_det
    return out


@njit(cache=_CACHE, nogil=True)
def gicp_linearise(src, src_cov, src_lab, rot, trans, map_pos, map_cov, map_lab, usable, grid, origin, dims, voxel,
                   radius, max_dist, semantic_label_filter, robust_scale):
    """One Gauss-Newton step of GICP: H, g of the Mahalanobis cost, plus counts of pairs found and kept.
    One thread on purpose: the registration worker shares its cores with inference in the pipeline."""
    h = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    found = 0
    kept = 0
    max_d2 = max_dist * max_dist
    q = np.empty(3)
    c = np.empty((3, 3))
    rc = np.empty((3, 3))
    j = np.zeros((3, 6))
    j[0, 3] = -1.0
    j[1, 4] = -1.0
    j[2, 5] = -1.0
    for n in range(src.shape[0]):
        for a in range(3):
            q[a] = rot[a, 0] * src[n, 0] + rot[a, 1] * src[n, 1] + rot[a, 2] * src[n, 2] + trans[a]
        m, d2 = nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius, usable)
        if m < 0 or d2 > max_d2:
            continue
        found += 1
        if semantic_label_filter and map_lab[m] != src_lab[n]:
            continue  # the semantic label filter: pairs whose labels differ do not constrain the pose
        kept += 1
        for a in range(3):  # c = map_cov + R src_cov R^T
            for b in range(3):
                rc[a, b] = rot[a, 0] * src_cov[n, 0, b] + rot[a, 1] * src_cov[n, 1, b] + rot[a, 2] * src_cov[n, 2, b]
        for a in range(3):
            for b in range(3):
                c[a, b] = map_cov[m, a, b] + rc[a, 0] * rot[b, 0] + rc[a, 1] * rot[b, 1] + rc[a, 2] * rot[b, 2]
        info = _inv3_sym(c)
        r0 = map_pos[m, 0] - q[0]
        r1 = map_pos[m, 1] - q[1]
        r2 = map_pos[m, 2] - q[2]
        # J = [[q]_x, -I]
        j[0, 1] = -q[2]
        j[0, 2] = q[1]
        j[1, 0] = q[2]
        j[1, 2] = -q[0]
        j[2, 0] = -q[1]
        j[2, 1] = q[0]
        ir0 = info[0, 0] * r0 + info[0, 1] * r1 + info[0, 2] * r2
        ir1 = info[1, 0] * r0 + info[1, 1] * r1 + info[1, 2] * r2
        ir2 = info[2, 0] * r0 + info[2, 1] * r1 + info[2, 2] * r2
        e = r0 * ir0 + r1 * ir1 + r2 * ir2
        cost += e
        # Cauchy weight on the Mahalanobis error: one bad pair cannot outvote a surface
        w = 1.0 if robust_scale <= 0.0 else 1.0 / (1.0 + e / robust_scale)
        for u in range(6):
            # (J^T info)[u, :]
            t0 = j[0, u] * info[0, 0] + j[1, u] * info[1, 0] + j[2, u] * info[2, 0]
            t1 = j[0, u] * info[0, 1] + j[1, u] * info[1, 1] + j[2, u] * info[2, 1]
            t2 = j[0, u] * info[0, 2] + j[1, u] * info[1, 2] + j[2, u] * info[2, 2]
            g[u] += w * (t0 * r0 + t1 * r1 + t2 * r2)
            for v in range(u, 6):
                h[u, v] += w * (t0 * j[0, v] + t1 * j[1, v] + t2 * j[2, v])
    for u in range(6):
        for v in range(u):
            h[u, v] = h[v, u]
    return h, g, cost, found, kept


@njit(cache=_CACHE, nogil=True)
def nearest_distances(queries, map_pos, grid, origin, dims, voxel, radius, usable):
    out = np.empty(queries.shape[0])
    idx = np.empty(queries.shape[0], np.int64)
    for n in range(queries.shape[0]):
        m, d2 = nearest_in_window(queries[n], map_pos, grid, origin, dims, voxel, radius, usable)
        idx[n] = m
        out[n] = np.sqrt(d2) if m >= 0 else np.inf
    return out, idx


@njit(cache=_CACHE, nogil=True)
def window_grid(keys, origin, dims):
    """Dense index of map voxels (integer keys) inside a window starting at origin."""
    grid = np.full(dims[0] * dims[1] * dims[2], -1, np.int32)
    for n in range(keys.shape[0]):
        i = keys[n, 0] - origin[0]
        j = keys[n, 1] - origin[1]
        k = keys[n, 2] - origin[2]
        if 0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]:
            grid[(i * dims[1] + j) * dims[2] + k] = n
    return grid


@njit(cache=_CACHE, nogil=True)
def assign_voxels(points, keys, map_pos, grid, origin, dims, voxel, merge_radius, map_rows, alive, n_map):
    """Map row of each frame point: the live map voxel holding it; else the nearest live map point within
    merge_radius (so a surface straddling a voxel boundary stays one voxel across frames and its p-index measures
    persistence, not aliasing); else a new row, numbered from n_map on, for its voxel.
    Returns (rows, first point of each new row). The grid is used up: new rows are written into it."""
    out = np.empty(keys.shape[0], np.int64)
    first_key = np.empty(keys.shape[0], np.int64)
    n_new = 0
    r2 = merge_radius * merge_radius
    for n in range(keys.shape[0]):
        cell = ((keys[n, 0] - origin[0]) * dims[1] + keys[n, 1] - origin[1]) * dims[2] + keys[n, 2] - origin[2]
        local = grid[cell]
        if local >= 0 and alive[local]:
            out[n] = map_rows[local]
            continue
        if local <= -3:  # a voxel this frame created
            out[n] = n_map + (-3 - local)
            continue
        if r2 > 0.0:
            m, d2 = nearest_in_window(points[n], map_pos, grid, origin, dims, voxel, 1, alive)
            if m >= 0 and d2 <= r2:
                out[n] = map_rows[m]
                continue
        out[n] = n_map + n_new
        first_key[n_new] = n
        grid[cell] = -3 - n_new  # later points in this voxel join the same new row
        n_new += 1
    return out, first_key[:n_new]


@njit(cache=_CACHE, nogil=True)
def rotate_covariances(cov, rot):
    """R C R^T for each C (numpy's batched matmul is slow for 3x3)."""
    out = np.empty_like(cov)
    tmp = np.empty((3, 3))
    for n in range(cov.shape[0]):
        for a in range(3):
            for b in range(3):
                tmp[a, b] = rot[a, 0] * cov[n, 0, b] + rot[a, 1] * cov[n, 1, b] + rot[a, 2] * cov[n, 2, b]
        for a in range(3):
            for b in range(3):
                out[n, a, b] = tmp[a, 0] * rot[b, 0] + tmp[a, 1] * rot[b, 1] + tmp[a, 2] * rot[b, 2]
    return out


@njit(cache=_CACHE, nogil=True)
def rows_in_box(keys, alive, lower, upper):
    """Rows of live voxels whose keys lie in [lower, upper]."""
    out = np.empty(keys.shape[0], np.int64)
    n_out = 0
    for n in range(keys.shape[0]):
        if not alive[n]:
            continue
        if (lower[0] <= keys[n, 0] <= upper[0] and lower[1] <= keys[n, 1] <= upper[1]
                and lower[2] <= keys[n, 2] <= upper[2]):
            out[n_out] = n
            n_out += 1
    return out[:n_out]


@njit(cache=_CACHE, nogil=True)
def merge_points(rows, pw, cw, labels, t, pos, cov, counts, label, t0, f, last, wacc, use_p_index):
    """Voxel PFilter merge, in place: each touched voxel becomes the weighted mean of its old point
    (weight f * p-index, or f without the filter) and the frame's points in it (weight 1 each)."""
    for n in range(rows.shape[0]):
        r = rows[n]
        if last[r] != t:  # first point of this frame in voxel r
            if f[r] > 0:
                w = f[r] * (f[r] / (t - t0[r])) if use_p_index else float(f[r])
            else:
                w = 0.0
            for a in range(3):
                pos[r, a] *= w
                for b in range(3):
                    cov[r, a, b] *= w
            wacc[r] = w
            f[r] += 1
            last[r] = t
        for a in range(3):
            pos[r, a] += pw[n, a]
            for b in range(3):
                cov[r, a, b] += cw[n, a, b]
        wacc[r] += 1.0
        counts[r, labels[n]] += 1
    for n in range(rows.shape[0]):
        r = rows[n]
        if wacc[r] > 0.0:
            inv = 1.0 / wacc[r]
            for a in range(3):
                pos[r, a] *= inv
                for b in range(3):
                    cov[r, a, b] *= inv
            wacc[r] = 0.0
            best = 0
            for c in range(counts.shape[1]):
                if counts[r, c] > counts[r, best]:
                    best = c
            label[r] = best


@njit(cache=_CACHE, nogil=True)
def pool_voxels(pos, cov, labels, keys, dims, n_classes):
    """Mean position and covariance and majority label of the points in each cell of a coarser grid."""
    n_cells = dims[0] * dims[1] * dims[2]
    slot = np.full(n_cells, -1, np.int64)
    out_pos = np.zeros((pos.shape[0], 3))
    out_cov = np.zeros((pos.shape[0], 3, 3))
    votes = np.zeros((pos.shape[0], n_classes), np.int32)
    count = np.zeros(pos.shape[0])
    out_keys = np.empty((pos.shape[0], 3), np.int64)
    n_out = 0
    for n in range(pos.shape[0]):
        i, j, k = keys[n, 0], keys[n, 1], keys[n, 2]
        if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2]:
            continue
        cell = (i * dims[1] + j) * dims[2] + k
        s = slot[cell]
        if s < 0:
            s = n_out
            slot[cell] = s
            out_keys[s, 0], out_keys[s, 1], out_keys[s, 2] = i, j, k
            n_out += 1
        for a in range(3):
            out_pos[s, a] += pos[n, a]
            for b in range(3):
                out_cov[s, a, b] += cov[n, a, b]
        votes[s, labels[n]] += 1
        count[s] += 1.0
    out_lab = np.empty(n_out, np.uint8)
    for s in range(n_out):
        for a in range(3):
            out_pos[s, a] /= count[s]
            for b in range(3):
                out_cov[s, a, b] /= count[s]
        best = 0
        for c in range(n_classes):
            if votes[s, c] > votes[s, best]:
                best = c
        out_lab[s] = best
    return out_pos[:n_out], out_cov[:n_out], out_lab, out_keys[:n_out]


@njit(cache=_CACHE, nogil=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=_CACHE, nogil=True)
def grid_clusters(points, eps):
    """Single-linkage clusters at distance eps, found through a grid of eps-sized cells (union-find)."""
    n = points.shape[0]
    parent = np.arange(n)
    if n == 0:
        return parent
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = points[:, a].min()
        hi[a] = points[:, a].max()
    dims = np.empty(3, np.int64)
    for a in range(3):
        dims[a] = int((hi[a] - lo[a]) / eps) + 1
    cell_of = np.empty(n, np.int64)
    for i in range(n):
        cell_of[i] = ((int((points[i, 0] - lo[0]) / eps) * dims[1] + int((points[i, 1] - lo[1]) / eps)) * dims[2]
                      + int((points[i, 2] - lo[2]) / eps))
    n_cells = dims[0] * dims[1] * dims[2]
    start = np.zeros(n_cells + 1, np.int64)  # counting sort: points of cell c are order[start[c]:start[c + 1]]
    for i in range(n):
        start[cell_of[i] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell_of[i]]] = i
        fill[cell_of[i]] += 1
    eps2 = eps * eps
    for i in range(n):
        ci = int((points[i, 0] - lo[0]) / eps)
        cj = int((points[i, 1] - lo[1]) / eps)
        ck = int((points[i, 2] - lo[2]) / eps)
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    a, b, c = ci + di, cj + dj, ck + dk
                    if a < 0 or b < 0 or c < 0 or a >= dims[0] or b >= dims[1] or c >= dims[2]:
                        continue
                    cell = (a * dims[1] + b) * dims[2] + c
                    for s in range(start[cell], start[cell + 1]):
                        j = order[s]
                        if j <= i:
                            continue
                        d0 = points[i, 0] - points[j, 0]
                        d1 = points[i, 1] - points[j, 1]
                        d2 = points[i, 2] - points[j, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
                            ri, rj = _find(parent, i), _find(parent, j)
                            if ri != rj:
                                parent[max(ri, rj)] = min(ri, rj)
    for i in range(n):
        parent[i] = _find(parent, i)
    return parent


@njit(cache=_CACHE, nogil=True)
def mark_observed(points, map_pos, grid, origin, dims, voxel, radius_m, map_rows, alive, f, last, t):
    """Count as seen at frame t every live voxel within radius_m of a frame point (once a frame): a surface that
    straddles a voxel boundary falls in either voxel from frame to frame, and must not lose its p-index for it."""
    r2 = radius_m * radius_m
    for n in range(points.shape[0]):
        ci = int(np.floor(points[n, 0] / voxel)) - origin[0]
        cj = int(np.floor(points[n, 1] / voxel)) - origin[1]
        ck = int(np.floor(points[n, 2] / voxel)) - origin[2]
        for i in range(ci - 1, ci + 2):
            if i < 0 or i >= dims[0]:
                continue
            for j in range(cj - 1, cj + 2):
                if j < 0 or j >= dims[1]:
                    continue
                base = (i * dims[1] + j) * dims[2]
                for k in range(ck - 1, ck + 2):
                    if k < 0 or k >= dims[2]:
                        continue
                    m = grid[base + k]
                    if m < 0 or not alive[m]:
                        continue
                    row = map_rows[m]
                    if last[row] == t:
                        continue
                    d0 = map_pos[m, 0] - points[n, 0]
                    d1 = map_pos[m, 1] - points[n, 1]
                    d2 = map_pos[m, 2] - points[n, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                        f[row] += 1
                        last[row] = t
