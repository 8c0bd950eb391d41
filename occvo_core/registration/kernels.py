"""Compiled inner loops. Every frame lives on a 0.4 m grid, so neighbour search is a dense-array lookup, not a tree.

The parallel kernels give the same bits on any number of threads: sums are taken over fixed slices and added in
order, and whatever depends on order (new row numbers, grid cells two voxels share) is done serially afterwards."""

from __future__ import annotations

import os

import numba
import numpy as np
from numba import njit, prange

if "NUMBA_THREADING_LAYER" not in os.environ:
    # streams registered side by side in threads of one worker launch parallel kernels at once: numba's default
    # fallback (workqueue) would abort on that, OpenMP and TBB take it (the variable survives numba's config reloads)
    os.environ["NUMBA_THREADING_LAYER"] = numba.config.THREADING_LAYER = "threadsafe"

_CACHE = True
CHUNKS = 16  # fixed slices of parallel loops (see above)


def use_threads(threads: int) -> None:
    """Kernel threads for calls from this Python thread: 0 = all cores (numba's thread count is per thread)."""
    most = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(most if threads <= 0 else min(threads, most))


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


@njit(cache=_CACHE, nogil=True)
def grid_indices(points, lower, voxel, shape):
    """Voxel indices floor((p - lower) / voxel) of each point, and how many fall outside the grid."""
    ijk = np.empty((points.shape[0], 3), np.int64)
    outside = 0
    for n in range(points.shape[0]):
        inside = True
        for a in range(3):
            v = int(np.floor((points[n, a] - lower[a]) / voxel))
            ijk[n, a] = v
            inside = inside and 0 <= v < shape[a]
        if not inside:
            outside += 1
    return ijk, outside


@njit(cache=_CACHE, nogil=True)
def surface_voxels(ijk, shape):
    """Indices of the points that are surface voxels (surface_mask) and the dense grid holding, for each, its rank
    among them: dense_index of the surface points, without a second grid."""
    grid = dense_index(ijk, shape)
    keep = np.flatnonzero(surface_mask(ijk, grid, shape))
    for n in range(ijk.shape[0]):
        grid[(ijk[n, 0] * shape[1] + ijk[n, 1]) * shape[2] + ijk[n, 2]] = -1
    for a in range(keep.shape[0]):
        n = keep[a]
        grid[(ijk[n, 0] * shape[1] + ijk[n, 1]) * shape[2] + ijk[n, 2]] = a
    return keep, grid


@njit(cache=_CACHE, nogil=True, inline="always")
def _source_block(ijk, n, f, shape):
    """(block of point n among the f^3 blocks of the grid, block parity)."""
    bi, bj, bk = ijk[n, 0] // f, ijk[n, 1] // f, ijk[n, 2] // f
    return (bi * ((shape[1] + f - 1) // f) + bj) * ((shape[2] + f - 1) // f) + bk, (bi + bj + bk) % 2


@njit(cache=_CACHE, nogil=True, inline="always")
def _cell_hash(ijk, n, shape):
    """A fixed pseudo-random number of point n's grid cell (splitmix64 of its index): picks by it favour no direction."""
    z = np.uint64((ijk[n, 0] * shape[1] + ijk[n, 1]) * shape[2] + ijk[n, 2]) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=_CACHE, nogil=True)
def thin_sources(ijk, ground, shape, wide, coarse, fine, fine_ground, pick=0):
    """The registration source sets, each one point of every factor^3 block of voxels (0: no set): one point per wide
    and per coarse block, and for fine one per fine block off the ground and per fine_ground block on it (the ground
    only holds z, roll and pitch). pick 0: the block's first point in the points' order, which grid order makes its
    rear-most (lowest x); 1 (balanced): its last (front-most) in blocks of odd parity; 2 (uniform): the point whose
    cell has the smallest fixed hash, so every voxel of a block is as likely a source and the picks lean no way.
    Indices ascending."""
    factors = (wide, coarse, fine, fine_ground)
    picks = []
    best = []
    for f in factors:
        g = max(f, 1)
        size = ((shape[0] + g - 1) // g) * ((shape[1] + g - 1) // g) * ((shape[2] + g - 1) // g)
        picks.append(np.full(size, -1, np.int32))
        best.append(np.zeros(size if pick == 2 else 1, np.uint64))
    out = np.empty((3, ijk.shape[0]), np.int64)
    count = np.zeros(3, np.int64)
    for n in range(ijk.shape[0]):
        h = _cell_hash(ijk, n, shape) if pick == 2 else np.uint64(0)
        for s in range(4):
            f = factors[s]
            if f == 0 or (s == 2 and ground[n]) or (s == 3 and not ground[n]):
                continue
            b, odd = _source_block(ijk, n, f, shape)
            if picks[s][b] < 0 and pick == 0:  # the first: listed at once, in point order
                o = min(s, 2)
                out[o, count[o]] = n
                count[o] += 1
            if picks[s][b] < 0 or (pick == 1 and odd == 1) or (pick == 2 and h < best[s][b]):
                picks[s][b] = n
                if pick == 2:
                    best[s][b] = h
    if pick != 0:  # the picks are final only now
        sets = [np.sort(p[p >= 0]).astype(np.int64) for p in picks]
        return sets[0], sets[1], np.sort(np.concatenate((sets[2], sets[3])))
    return out[0, :count[0]].copy(), out[1, :count[1]].copy(), out[2, :count[2]].copy()


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


@njit(cache=_CACHE, nogil=True, parallel=True)
def plane_covariances(points, ijk, grid, shape, radius, epsilon):
    """GICP covariances (Segal et al.): the neighbourhood's plane, as eps along its normal and 1 across it."""
    n_pts = points.shape[0]
    covs = np.empty((n_pts, 3, 3))
    for n in prange(n_pts):
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
        s = 1.0 - epsilon
        covs[n, 0, 0] = 1.0 - s * nx * nx
        covs[n, 1, 1] = 1.0 - s * ny * ny
        covs[n, 2, 2] = 1.0 - s * nz * nz
        covs[n, 0, 1] = covs[n, 1, 0] = -s * nx * ny
        covs[n, 0, 2] = covs[n, 2, 0] = -s * nx * nz
        covs[n, 1, 2] = covs[n, 2, 1] = -s * ny * nz
    return covs


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


@njit(cache=_CACHE, nogil=True, inline="always")
def _inv3_sym(a, b, c, d, e, f):
    """Inverse of the symmetric positive-definite [[a b c] [b d e] [c e f]] by cofactors, as its six entries."""
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    inv_det = 1.0 / (a * A + b * B + c * C)
    return (A * inv_det, B * inv_det, C * inv_det, (a * f - c * c) * inv_det, (b * c - a * e) * inv_det,
            (a * d - b * b) * inv_det)


@njit(cache=_CACHE, nogil=True, inline="always")
def _add_pair(n, m, src, src_cov, rot, trans, map_pos, map_cov, robust_scale, out):
    """Add the GICP terms of the pair (source n, map point m) into out = (H upper triangle 21, g 6, cost, ...)."""
    q0 = rot[0, 0] * src[n, 0] + rot[0, 1] * src[n, 1] + rot[0, 2] * src[n, 2] + trans[0]
    q1 = rot[1, 0] * src[n, 0] + rot[1, 1] * src[n, 1] + rot[1, 2] * src[n, 2] + trans[1]
    q2 = rot[2, 0] * src[n, 0] + rot[2, 1] * src[n, 1] + rot[2, 2] * src[n, 2] + trans[2]
    # c = map_cov + R src_cov R^T (symmetric: six entries)
    rc00 = rot[0, 0] * src_cov[n, 0, 0] + rot[0, 1] * src_cov[n, 1, 0] + rot[0, 2] * src_cov[n, 2, 0]
    rc01 = rot[0, 0] * src_cov[n, 0, 1] + rot[0, 1] * src_cov[n, 1, 1] + rot[0, 2] * src_cov[n, 2, 1]
    rc02 = rot[0, 0] * src_cov[n, 0, 2] + rot[0, 1] * src_cov[n, 1, 2] + rot[0, 2] * src_cov[n, 2, 2]
    rc10 = rot[1, 0] * src_cov[n, 0, 0] + rot[1, 1] * src_cov[n, 1, 0] + rot[1, 2] * src_cov[n, 2, 0]
    rc11 = rot[1, 0] * src_cov[n, 0, 1] + rot[1, 1] * src_cov[n, 1, 1] + rot[1, 2] * src_cov[n, 2, 1]
    rc12 = rot[1, 0] * src_cov[n, 0, 2] + rot[1, 1] * src_cov[n, 1, 2] + rot[1, 2] * src_cov[n, 2, 2]
    rc20 = rot[2, 0] * src_cov[n, 0, 0] + rot[2, 1] * src_cov[n, 1, 0] + rot[2, 2] * src_cov[n, 2, 0]
    rc21 = rot[2, 0] * src_cov[n, 0, 1] + rot[2, 1] * src_cov[n, 1, 1] + rot[2, 2] * src_cov[n, 2, 1]
    rc22 = rot[2, 0] * src_cov[n, 0, 2] + rot[2, 1] * src_cov[n, 1, 2] + rot[2, 2] * src_cov[n, 2, 2]
    c00 = map_cov[m, 0, 0] + rc00 * rot[0, 0] + rc01 * rot[0, 1] + rc02 * rot[0, 2]
    c01 = map_cov[m, 0, 1] + rc00 * rot[1, 0] + rc01 * rot[1, 1] + rc02 * rot[1, 2]
    c02 = map_cov[m, 0, 2] + rc00 * rot[2, 0] + rc01 * rot[2, 1] + rc02 * rot[2, 2]
    c11 = map_cov[m, 1, 1] + rc10 * rot[1, 0] + rc11 * rot[1, 1] + rc12 * rot[1, 2]
    c12 = map_cov[m, 1, 2] + rc10 * rot[2, 0] + rc11 * rot[2, 1] + rc12 * rot[2, 2]
    c22 = map_cov[m, 2, 2] + rc20 * rot[2, 0] + rc21 * rot[2, 1] + rc22 * rot[2, 2]
    i00, i01, i02, i11, i12, i22 = _inv3_sym(c00, c01, c02, c11, c12, c22)
    r0 = map_pos[m, 0] - q0
    r1 = map_pos[m, 1] - q1
    r2 = map_pos[m, 2] - q2
    ir0 = i00 * r0 + i01 * r1 + i02 * r2
    ir1 = i01 * r0 + i11 * r1 + i12 * r2
    ir2 = i02 * r0 + i12 * r1 + i22 * r2
    e = r0 * ir0 + r1 * ir1 + r2 * ir2
    out[27] += e
    # Cauchy weight on the Mahalanobis error: one bad pair cannot outvote a surface
    w = 1.0 if robust_scale <= 0.0 else 1.0 / (1.0 + e / robust_scale)
    # J = [[q]_x, -I]: columns (0, q2, -q1), (-q2, 0, q0), (q1, -q0, 0), -e_x, -e_y, -e_z. T = J^T info (6 x 3)
    t = ((q2 * i01 - q1 * i02, q2 * i11 - q1 * i12, q2 * i12 - q1 * i22),
         (-q2 * i00 + q0 * i02, -q2 * i01 + q0 * i12, -q2 * i02 + q0 * i22),
         (q1 * i00 - q0 * i01, q1 * i01 - q0 * i11, q1 * i02 - q0 * i12),
         (-i00, -i01, -i02), (-i01, -i11, -i12), (-i02, -i12, -i22))
    cols = ((0.0, q2, -q1), (-q2, 0.0, q0), (q1, -q0, 0.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
    k = 0
    for u in range(6):
        tu = t[u]
        out[21 + u] += w * (tu[0] * r0 + tu[1] * r1 + tu[2] * r2)
        for v in range(u, 6):
            cv = cols[v]
            out[k] += w * (tu[0] * cv[0] + tu[1] * cv[1] + tu[2] * cv[2])
            k += 1


@njit(cache=_CACHE, nogil=True)
def _linearise_range(lo, hi, src, src_cov, src_lab, rot, trans, map_pos, map_cov, map_lab, usable, grid, origin, dims,
                     voxel, radius, max_d2, semantic_label_filter, robust_scale, pairs, out):
    """Search the nearest map point of sources lo..hi, record it in pairs (-1: none kept) and add the GICP terms
    of the kept pairs into out = (H upper triangle 21, g 6, cost, found, kept)."""
    q = np.empty(3)
    for n in range(lo, hi):
        pairs[n] = -1
        for a in range(3):
            q[a] = rot[a, 0] * src[n, 0] + rot[a, 1] * src[n, 1] + rot[a, 2] * src[n, 2] + trans[a]
        m, d2 = nearest_in_window(q, map_pos, grid, origin, dims, voxel, radius, usable)
        if m < 0 or d2 > max_d2:
            continue
        out[28] += 1.0
        if semantic_label_filter and map_lab[m] != src_lab[n]:
            continue  # the semantic label filter: pairs whose labels differ do not constrain the pose
        out[29] += 1.0
        pairs[n] = m
        _add_pair(n, m, src, src_cov, rot, trans, map_pos, map_cov, robust_scale, out)


@njit(cache=_CACHE, nogil=True)
def _sum_parts(parts):
    total = np.zeros(parts.shape[1])
    for c in range(parts.shape[0]):
        for i in range(parts.shape[1]):
            total[i] += parts[c, i]
    h = np.empty((6, 6))
    k = 0
    for u in range(6):
        for v in range(u, 6):
            h[u, v] = h[v, u] = total[k]
            k += 1
    return h, total[21:27].copy(), total[27], int(total[28]), int(total[29])


@njit(cache=_CACHE, nogil=True, parallel=True)
def gicp_linearise_pairs(src, src_cov, rot, trans, map_pos, map_cov, pairs, robust_scale):
    """gicp_linearise at a new pose with the pairs of an earlier search kept (the pose moved too little since
    to change which map point is nearest, so the search, most of the cost, is skipped)."""
    n = src.shape[0]
    parts = np.zeros((CHUNKS, 30))
    for c in prange(CHUNKS):
        for i in range(n * c // CHUNKS, n * (c + 1) // CHUNKS):
            if pairs[i] >= 0:
                parts[c, 29] += 1.0
                _add_pair(i, pairs[i], src, src_cov, rot, trans, map_pos, map_cov, robust_scale, parts[c])
    return _sum_parts(parts)


@njit(cache=_CACHE, nogil=True, parallel=True)
def gicp_linearise(src, src_cov, src_lab, rot, trans, map_pos, map_cov, map_lab, usable, grid, origin, dims, voxel,
                   radius, max_dist, semantic_label_filter, robust_scale, pairs=None):
    """One Gauss-Newton step of GICP: H, g of the Mahalanobis cost, plus counts of pairs found and kept; the kept
    pairs go into `pairs` (map index per source, -1 none) when given.
    Sums run over CHUNKS fixed slices of the sources, added in order."""
    n = src.shape[0]
    if pairs is None:
        pairs = np.empty(n, np.int64)
    parts = np.zeros((CHUNKS, 30))
    max_d2 = max_dist * max_dist
    for c in prange(CHUNKS):
        _linearise_range(n * c // CHUNKS, n * (c + 1) // CHUNKS, src, src_cov, src_lab, rot, trans, map_pos, map_cov,
                         map_lab, usable, grid, origin, dims, voxel, radius, max_d2, semantic_label_filter, robust_scale,
                         pairs, parts[c])
    return _sum_parts(parts)


@njit(cache=_CACHE, nogil=True)
def nearest_distances(queries, map_pos, grid, origin, dims, voxel, radius, usable):
    out = np.empty(queries.shape[0])
    idx = np.empty(queries.shape[0], np.int64)
    for n in range(queries.shape[0]):
        m, d2 = nearest_in_window(queries[n], map_pos, grid, origin, dims, voxel, radius, usable)
        idx[n] = m
        out[n] = np.sqrt(d2) if m >= 0 else np.inf
    return out, idx


@njit(cache=_CACHE, nogil=True, parallel=True)
def assign_voxels(points, keys, map_pos, grid, origin, dims, voxel, merge_radius, map_rows, alive, n_map):
    """Map row of each frame point: the live map voxel holding it; else the nearest live map point within
    merge_radius (so a surface straddling a voxel boundary stays one voxel across frames and its p-index measures
    persistence, not aliasing); else a new row, numbered from n_map on, for its voxel.
    Returns (rows, first point of each new row). The grid is used up: new rows are written into it."""
    n_pts = keys.shape[0]
    out = np.empty(n_pts, np.int64)
    near = np.empty(n_pts, np.int64)
    cells = np.empty(n_pts, np.int64)
    r2 = merge_radius * merge_radius
    # lookups in the map's own voxels, in parallel (new rows never take part in them) ...
    for n in prange(n_pts):
        cell = ((keys[n, 0] - origin[0]) * dims[1] + keys[n, 1] - origin[1]) * dims[2] + keys[n, 2] - origin[2]
        cells[n] = cell
        out[n] = near[n] = -1
        local = grid[cell]
        if local >= 0 and alive[local]:
            out[n] = map_rows[local]
        elif r2 > 0.0:
            m, d2 = nearest_in_window(points[n], map_pos, grid, origin, dims, voxel, 1, alive)
            if m >= 0 and d2 <= r2:
                near[n] = map_rows[m]
    # ... then, in point order, a voxel this frame created before the nearest map point, else a new row
    first_key = np.empty(n_pts, np.int64)
    n_new = 0
    for n in range(n_pts):
        if out[n] >= 0:
            continue
        local = grid[cells[n]]
        if local <= -3:
            out[n] = n_map + (-3 - local)
        elif near[n] >= 0:
            out[n] = near[n]
        else:
            out[n] = n_map + n_new
            first_key[n_new] = n
            grid[cells[n]] = -3 - n_new  # later points in this voxel join the same new row
            n_new += 1
    return out, first_key[:n_new]


@njit(cache=_CACHE, nogil=True, parallel=True)
def rotate_covariances(cov, rot):
    """R C R^T for each C (numpy's batched matmul is slow for 3x3)."""
    out = np.empty_like(cov)
    for n in prange(cov.shape[0]):
        for a in range(3):
            t0 = rot[a, 0] * cov[n, 0, 0] + rot[a, 1] * cov[n, 1, 0] + rot[a, 2] * cov[n, 2, 0]
            t1 = rot[a, 0] * cov[n, 0, 1] + rot[a, 1] * cov[n, 1, 1] + rot[a, 2] * cov[n, 2, 1]
            t2 = rot[a, 0] * cov[n, 0, 2] + rot[a, 1] * cov[n, 1, 2] + rot[a, 2] * cov[n, 2, 2]
            for b in range(3):
                out[n, a, b] = t0 * rot[b, 0] + t1 * rot[b, 1] + t2 * rot[b, 2]
    return out


@njit(cache=_CACHE, nogil=True, inline="always")
def _rigid_motion(rot, trans, g, p0, p1, p2, c, out_pos, out_cov):
    """R p + t into out_pos (3,) and R C R^T into out_cov (3,3) for motion g; c must not be out_cov."""
    for a in range(3):
        out_pos[a] = rot[g, a, 0] * p0 + rot[g, a, 1] * p1 + rot[g, a, 2] * p2 + trans[g, a]
        t0 = rot[g, a, 0] * c[0, 0] + rot[g, a, 1] * c[1, 0] + rot[g, a, 2] * c[2, 0]
        t1 = rot[g, a, 0] * c[0, 1] + rot[g, a, 1] * c[1, 1] + rot[g, a, 2] * c[2, 1]
        t2 = rot[g, a, 0] * c[0, 2] + rot[g, a, 1] * c[1, 2] + rot[g, a, 2] * c[2, 2]
        for b in range(3):
            out_cov[a, b] = t0 * rot[g, b, 0] + t1 * rot[g, b, 1] + t2 * rot[g, b, 2]


@njit(cache=_CACHE, nogil=True, parallel=True)
def rigid_motions(pos, cov, rot, trans, group):
    """Each point and covariance moved by the rotation and translation of its group: R p + t, R C R^T (a loop
    closure moves each voxel with the frame that made it; numpy's batched 3x3 products are slow)."""
    out_pos = np.empty_like(pos)
    out_cov = np.empty_like(cov)
    for n in prange(pos.shape[0]):
        _rigid_motion(rot, trans, group[n], pos[n, 0], pos[n, 1], pos[n, 2], cov[n], out_pos[n], out_cov[n])
    return out_pos, out_cov


@njit(cache=_CACHE, nogil=True)
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
        _rigid_motion(rot, trans, group[n], p0, p1, p2, c, pos[r], cov[r])
        d0, d1, d2 = pos[r, 0] - p0, pos[r, 1] - p1, pos[r, 2] - p2
        far[n] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > voxel
        for a in range(3):
            keys[r, a] = np.int64(np.floor(pos[r, a] / voxel))
        box[0] = min(box[0], p0, pos[r, 0])
        box[1] = min(box[1], p1, pos[r, 1])
        box[2] = max(box[2], p0, pos[r, 0])
        box[3] = max(box[3], p1, pos[r, 1])
    return far


@njit(cache=_CACHE, nogil=True)
def claim_cells(keys, rows, grid, origin, dims):
    """Which moved rows may stay: those whose cell holds no voxel of the window grid and no earlier moved row (in
    row order: the first stands). Claimed cells are marked -2 in grid (an empty cell to nearest_in_window)."""
    keep = np.empty(rows.shape[0], np.bool_)
    for n in range(rows.shape[0]):
        r = rows[n]
        cell = ((keys[r, 0] - origin[0]) * dims[1] + keys[r, 1] - origin[1]) * dims[2] + keys[r, 2] - origin[2]
        keep[n] = grid[cell] == -1
        grid[cell] = -2 if keep[n] else grid[cell]
    return keep


@njit(cache=_CACHE, nogil=True, parallel=True)
def merge_points(rows, pw, cw, labels, t, pos, cov, counts, label, t0, f, last, wacc, use_p_index, changed, parts):
    """Voxel PFilter merge, in place: each touched voxel becomes the weighted mean of its old point
    (weight f * p-index, or f without the filter) and the frame's points in it (weight 1 each).
    changed (xmin, ymin, xmax, ymax) grows to hold every touched voxel before and after."""
    # part c (one a thread) owns the rows r with (r // 64) % parts == c and adds their points in point order, so every
    # voxel sums the same numbers in the same order for any number of parts (blocks of 64 rows: no shared cache lines)
    boxes = np.empty((parts, 4))
    for c in prange(parts):
        box = boxes[c]
        box[0] = box[1] = np.inf
        box[2] = box[3] = -np.inf
        for n in range(rows.shape[0]):
            r = rows[n]
            if (r >> 6) % parts != c:
                continue
            if last[r] != t:  # first point of this frame in voxel r
                if f[r] > 0:
                    _grow_box(box, pos[r, 0], pos[r, 1])
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
            if (r >> 6) % parts != c or wacc[r] <= 0.0:
                continue
            inv = 1.0 / wacc[r]
            for a in range(3):
                pos[r, a] *= inv
                for b in range(3):
                    cov[r, a, b] *= inv
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


@njit(cache=_CACHE, nogil=True, parallel=True)
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


@njit(cache=_CACHE, nogil=True, parallel=True)
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


@njit(cache=_CACHE, nogil=True)
def _cell_sort(points, cell):
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
        cell_of[i] = ((int((points[i, 0] - lo[0]) / cell) * dims[1] + int((points[i, 1] - lo[1]) / cell)) * dims[2]
                      + int((points[i, 2] - lo[2]) / cell))
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(n):
        start[cell_of[i] + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell_of[i]]] = i
        fill[cell_of[i]] += 1
    return lo, dims, start, order


@njit(cache=_CACHE, nogil=True)
def near_any(queries, points, radius):
    """For each query, whether some point lies within radius (distance not above it), through a grid of
    radius-sized cells over the points (counting sort)."""
    out = np.zeros(queries.shape[0], np.bool_)
    if points.shape[0] == 0:
        return out
    lo, dims, start, order = _cell_sort(points, radius)
    for q in range(queries.shape[0]):
        c = np.empty(3, np.int64)
        for a in range(3):
            c[a] = int(np.floor((queries[q, a] - lo[a]) / radius))
        found = False
        for i in range(max(c[0] - 1, 0), min(c[0] + 2, dims[0])):
            for j in range(max(c[1] - 1, 0), min(c[1] + 2, dims[1])):
                for k in range(max(c[2] - 1, 0), min(c[2] + 2, dims[2])):
                    cell = (i * dims[1] + j) * dims[2] + k
                    for s in range(start[cell], start[cell + 1]):
                        p = order[s]
                        d0 = queries[q, 0] - points[p, 0]
                        d1 = queries[q, 1] - points[p, 1]
                        d2 = queries[q, 2] - points[p, 2]
                        if not np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > radius:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            if found:
                break
        out[q] = found
    return out


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
    lo, dims, start, order = _cell_sort(points, eps)
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


@njit(cache=_CACHE, nogil=True, inline="always")
def _grow_box(box, x, y):
    box[0] = min(box[0], x)
    box[1] = min(box[1], y)
    box[2] = max(box[2], x)
    box[3] = max(box[3], y)


@njit(cache=_CACHE, nogil=True, parallel=True)
def mark_observed(points, map_pos, grid, origin, dims, voxel, radius_m, map_rows, alive, f, last, t, changed):
    """Count as seen at frame t every live voxel within radius_m of a frame point (once a frame): a surface that
    straddles a voxel boundary falls in either voxel from frame to frame, and must not lose its p-index for it.
    changed grows to hold the voxels counted."""
    r2 = radius_m * radius_m
    n_win = map_rows.shape[0]
    # window-local "already counted at t": neighbouring frame points test the same voxels many times over
    counted = np.empty(n_win, np.bool_)
    for m in range(n_win):
        counted[m] = last[map_rows[m]] == t or not alive[m]
    seen = counted.copy()  # threads only ever write True here, so any interleaving gives the same set
    n_pts = points.shape[0]
    for c in prange(CHUNKS):
        for n in range(n_pts * c // CHUNKS, n_pts * (c + 1) // CHUNKS):
            ci = int(np.floor(points[n, 0] / voxel)) - origin[0]
            cj = int(np.floor(points[n, 1] / voxel)) - origin[1]
            ck = int(np.floor(points[n, 2] / voxel)) - origin[2]
            for i in range(max(ci - 1, 0), min(ci + 2, dims[0])):
                for j in range(max(cj - 1, 0), min(cj + 2, dims[1])):
                    base = (i * dims[1] + j) * dims[2]
                    for k in range(max(ck - 1, 0), min(ck + 2, dims[2])):
                        m = grid[base + k]
                        if m < 0 or seen[m]:
                            continue
                        d0 = map_pos[m, 0] - points[n, 0]
                        d1 = map_pos[m, 1] - points[n, 1]
                        d2 = map_pos[m, 2] - points[n, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                            seen[m] = True
    for m in range(n_win):
        if seen[m] and not counted[m]:
            _grow_box(changed, map_pos[m, 0], map_pos[m, 1])
            row = map_rows[m]
            f[row] += 1
            last[row] = t


@njit(cache=_CACHE, nogil=True)
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
        if use_p_index and not f[r] / max(last[r] - t0[r] + 1 - between[r], 1) > threshold:
            continue
        out[n_out] = r
        n_out += 1
    return out[:n_out]


@njit(cache=_CACHE, nogil=True)
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


@njit(cache=_CACHE, nogil=True)
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


@njit(cache=_CACHE, nogil=True, parallel=True)
def window_voxels(keys, alive, f, t0, pos, label, n, lower, upper, t):
    """Live rows < n with keys in [lower, upper], in row order, with copies of their positions and labels, their
    p-index f / max(t - t0, 1), and the dense grid of the box holding each one's window index (one pass, not five)."""
    dims = upper - lower + 1
    n_cells = dims[0] * dims[1] * dims[2]
    grid = np.empty(n_cells, np.int32)
    for c in prange(CHUNKS):
        grid[n_cells * c // CHUNKS: n_cells * (c + 1) // CHUNKS] = -1
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
        p_index[a] = f[r] / max(t - t0[r], 1)
    for a in range(m):  # in row order: a later row with the same key wins
        r = rows[a]
        grid[((keys[r, 0] - lower[0]) * dims[1] + keys[r, 1] - lower[1]) * dims[2] + keys[r, 2] - lower[2]] = a
    return rows, out_pos, out_label, p_index, grid


# -- copies of whole map arrays without the GIL: numpy's copies of a map's arrays (100 MB and more when its capacity
# doubles, it is compacted or snapshotted) held the GIL for up to 100 ms, stalling every other thread of the worker

@njit(cache=_CACHE, nogil=True)
def copy_row_bytes(dst, src, n):
    """dst[:n] = src[:n] for C-contiguous (rows, bytes per row) uint8 views."""
    d, s = dst.reshape(-1), src.reshape(-1)
    for k in range(n * src.shape[1]):
        d[k] = s[k]


@njit(cache=_CACHE, nogil=True)
def gather_row_bytes(arr, keep):
    """arr[i] = arr[keep[i]] in place for increasing keep (keep[i] >= i: no row is read after it was written)."""
    w = arr.shape[1]
    for i in range(keep.size):
        k = keep[i]
        if k != i:
            for j in range(w):
                arr[i, j] = arr[k, j]
