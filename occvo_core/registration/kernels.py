"""Compiled inner loops. Every frame lives on a 0.4 m grid, so neighbour search is a dense-array lookup, not a tree."""

from __future__ import annotations

import numpy as np
from numba import njit

_CACHE = True


@njit(cache=_CACHE)
def jacobi_eigh3(a):
    """Eigenvalues (ascending) and eigenvectors (columns) of a symmetric 3x3 matrix by cyclic Jacobi sweeps."""
    m = a.copy()
    v = np.eye(3)
    for _ in range(12):
        off = m[0, 1] ** 2 + m[0, 2] ** 2 + m[1, 2] ** 2
        if off < 1e-22:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if abs(m[p, q]) < 1e-30:
                continue
            theta = (m[q, q] - m[p, p]) / (2.0 * m[p, q])
            t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # m = J^T m J
                mkp, mkq = m[k, p], m[k, q]
                m[k, p] = c * mkp - s * mkq
                m[k, q] = s * mkp + c * mkq
            for k in range(3):
                mpk, mqk = m[p, k], m[q, k]
                m[p, k] = c * mpk - s * mqk
                m[q, k] = s * mpk + c * mqk
            for k in range(3):
                vkp, vkq = v[k, p], v[k, q]
                v[k, p] = c * vkp - s * vkq
                v[k, q] = s * vkp + c * vkq
    w = np.array([m[0, 0], m[1, 1], m[2, 2]])
    order = np.argsort(w)
    return w[order], v[:, order]


@njit(cache=_CACHE)
def dense_index(ijk, shape):
    """Flat dense grid holding each point's row index (-1 = empty); points outside the grid are left out."""
    grid = np.full(shape[0] * shape[1] * shape[2], -1, np.int32)
    for n in range(ijk.shape[0]):
        i, j, k = ijk[n, 0], ijk[n, 1], ijk[n, 2]
        if 0 <= i < shape[0] and 0 <= j < shape[1] and 0 <= k < shape[2]:
            grid[(i * shape[1] + j) * shape[2] + k] = n
    return grid


@njit(cache=_CACHE)
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


@njit(cache=_CACHE)
def plane_covariances(points, ijk, grid, shape, radius, epsilon):
    """GICP covariances (Segal et al.): neighbourhood covariance with eigenvalues replaced by (eps, 1, 1)."""
    n_pts = points.shape[0]
    covs = np.empty((n_pts, 3, 3))
    s = np.zeros(3)
    ss = np.zeros((3, 3))
    for n in range(n_pts):
        s[:] = 0.0
        ss[:] = 0.0
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
                    p = points[m]
                    cnt += 1
                    for a in range(3):
                        s[a] += p[a]
                        for b in range(3):
                            ss[a, b] += p[a] * p[b]
        if cnt < 3:  # too few neighbours for a surface: isotropic
            covs[n] = np.eye(3)
            continue
        for a in range(3):
            s[a] /= cnt
        for a in range(3):
            for b in range(3):
                ss[a, b] = ss[a, b] / cnt - s[a] * s[b]
        _, vec = jacobi_eigh3(ss)
        for a in range(3):
            for b in range(3):
                covs[n, a, b] = (epsilon * vec[a, 0] * vec[b, 0] + vec[a, 1] * vec[b, 1] + vec[a, 2] * vec[b, 2])
    return covs


@njit(cache=_CACHE)
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


@njit(cache=_CACHE)
def nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius):
    """Nearest map point to q within `radius` voxel rings: (index or -1, squared distance).

    Rings are searched outwards; after ring r every unsearched point is at least r voxels away, so the search
    stops as soon as the best distance is below that."""
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
                        if m >= 0:
                            d0 = map_pos[m, 0] - q[0]
                            d1 = map_pos[m, 1] - q[1]
                            d2 = map_pos[m, 2] - q[2]
                            d = d0 * d0 + d1 * d1 + d2 * d2
                            if d < best_d2:
                                best_d2 = d
                                best = m
                    dk += step if step > 0 else 1
        if best >= 0 and best_d2 <= (r * voxel) ** 2:
            break
    return best, best_d2


@njit(cache=_CACHE)
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


@njit(cache=_CACHE)
def gicp_linearise(src, src_cov, src_lab, rot, trans, map_pos, map_cov, map_lab, grid, origin, dims, voxel, radius,
                   max_dist, semantic_label_filter, robust_scale):
    """One Gauss-Newton step of GICP: H, g of the Mahalanobis cost, plus counts of pairs found and kept."""
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
        m, d2 = nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius)
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


@njit(cache=_CACHE)
def nearest_distances(queries, map_pos, grid, origin, dims, voxel, radius):
    out = np.empty(queries.shape[0])
    idx = np.empty(queries.shape[0], np.int64)
    for n in range(queries.shape[0]):
        m, d2 = nearest_in_window(queries[n], map_pos, grid, origin, dims, voxel, radius)
        idx[n] = m
        out[n] = np.sqrt(d2) if m >= 0 else np.inf
    return out, idx


@njit(cache=_CACHE)
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


@njit(cache=_CACHE)
def assign_voxels(points, keys, map_pos, grid, origin, dims, voxel, merge_radius, map_rows, n_map):
    """Map row of each frame point: the nearest existing map point within merge_radius (that voxel is observed again),
    else the voxel holding the point, created as a new row (numbered from n_map on) when empty.

    Joining the nearest point rather than the enclosing voxel keeps a surface that straddles a voxel boundary in one
    voxel across frames, so its p-index measures persistence, not aliasing. Returns (rows, first point of each new row)."""
    out = np.empty(keys.shape[0], np.int64)
    first_key = np.empty(keys.shape[0], np.int64)
    n_new = 0
    r2 = merge_radius * merge_radius
    for n in range(keys.shape[0]):
        m, d2 = nearest_in_window(points[n], map_pos, grid, origin, dims, voxel, 1)
        if m >= 0 and d2 <= r2:
            out[n] = map_rows[m]
            continue
        cell = ((keys[n, 0] - origin[0]) * dims[1] + keys[n, 1] - origin[1]) * dims[2] + keys[n, 2] - origin[2]
        local = grid[cell]
        if local >= 0:
            out[n] = map_rows[local]
        elif local == -1:
            out[n] = n_map + n_new
            first_key[n_new] = n
            grid[cell] = -3 - n_new  # later points in this voxel join the same new row
            n_new += 1
        else:
            out[n] = n_map + (-3 - local)
    return out, first_key[:n_new]


@njit(cache=_CACHE)
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
            pos[r] *= w
            cov[r] *= w
            wacc[r] = w
            f[r] += 1
            last[r] = t
        pos[r] += pw[n]
        cov[r] += cw[n]
        wacc[r] += 1.0
        counts[r, labels[n]] += 1
    for n in range(rows.shape[0]):
        r = rows[n]
        if wacc[r] > 0.0:
            pos[r] /= wacc[r]
            cov[r] /= wacc[r]
            wacc[r] = 0.0
            label[r] = np.argmax(counts[r])
