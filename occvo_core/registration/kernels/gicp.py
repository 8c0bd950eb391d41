"""GICP's linearisation: one pair's terms of H and g (_add_pair), summed over fixed slices of the sources; the search
and the Gauss-Newton loop are in gicp_loop.py."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occvo_core.registration.kernels import CACHE, CHUNKS


@njit(cache=CACHE, nogil=True, inline="always")
def _inv3_sym(a, b, c, d, e, f):
    """Inverse of the symmetric positive-definite [[a b c] [b d e] [c e f]] by cofactors, as its six entries."""
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    inv_det = 1.0 / (a * A + b * B + c * C)
    return (
        A * inv_det,
        B * inv_det,
        C * inv_det,
        (a * f - c * c) * inv_det,
        (b * c - a * e) * inv_det,
        (a * d - b * b) * inv_det,
    )


@njit(cache=CACHE, nogil=True, inline="always")
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
    t = (
        (q2 * i01 - q1 * i02, q2 * i11 - q1 * i12, q2 * i12 - q1 * i22),
        (-q2 * i00 + q0 * i02, -q2 * i01 + q0 * i12, -q2 * i02 + q0 * i22),
        (q1 * i00 - q0 * i01, q1 * i01 - q0 * i11, q1 * i02 - q0 * i12),
        (-i00, -i01, -i02),
        (-i01, -i11, -i12),
        (-i02, -i12, -i22),
    )
    cols = ((0.0, q2, -q1), (-q2, 0.0, q0), (q1, -q0, 0.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
    k = 0
    for u in range(6):
        tu = t[u]
        out[21 + u] += w * (tu[0] * r0 + tu[1] * r1 + tu[2] * r2)
        for v in range(u, 6):
            cv = cols[v]
            out[k] += w * (tu[0] * cv[0] + tu[1] * cv[1] + tu[2] * cv[2])
            k += 1


@njit(cache=CACHE, nogil=True)
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


@njit(cache=CACHE, nogil=True, parallel=True)
def gicp_linearise_pairs(src, src_cov, rot, trans, map_pos, map_cov, pairs, robust_scale):
    """gicp_linearise (kernels/gicp_loop.py) at a new pose with the pairs of an earlier search kept (the pose moved too little since
    to change which map point is nearest, so the search, most of the cost, is skipped)."""
    n = src.shape[0]
    parts = np.zeros((CHUNKS, 30))
    for c in prange(CHUNKS):
        for i in range(n * c // CHUNKS, n * (c + 1) // CHUNKS):
            if pairs[i] >= 0:
                parts[c, 29] += 1.0
                _add_pair(i, pairs[i], src, src_cov, rot, trans, map_pos, map_cov, robust_scale, parts[c])
    return _sum_parts(parts)
