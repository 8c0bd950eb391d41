"""GICP's Gauss-Newton loop compiled whole: search, linearise, solve, step and convergence test without a return to
Python between iterations, and each source's nearest map point kept while it provably stays nearest."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occvo_core.registration.kernels import CACHE, CHUNKS
from occvo_core.registration.kernels.gicp import _add_pair, _sum_parts, gicp_linearise_pairs
from occvo_core.registration.kernels.nearest_bound import nearest_bounded, still_nearest
from occvo_core.registration.kernels.numpy_blas import inv, norm, solve
from occvo_core.registration.kernels.se3 import moved_beyond, se3_exp_left
from occvo_core.registration.semantic_label_filter import semantic_label_filter


@njit(cache=CACHE, nogil=True, parallel=True)
def _linearise_kept(
    src,
    src_cov,
    src_lab,
    rot,
    trans,
    map_pos,
    map_cov,
    map_lab,
    usable,
    grid,
    origin,
    dims,
    voxel,
    radius,
    max_d2,
    label_filter,
    robust_scale,
    pairs,
    near,
    bound2,
    searched_q,
):
    """gicp_linearise's answer, searching only the sources whose nearest map point (near, bound2, searched_q: each
    one's last search) may have changed. Sums run over CHUNKS fixed slices of the sources, added in order."""
    n = src.shape[0]
    parts = np.zeros((CHUNKS, 30))
    for c in prange(CHUNKS):
        out = parts[c]
        q = np.empty(3)
        gaps = np.empty((3, 2 * radius + 1))
        for i in range(n * c // CHUNKS, n * (c + 1) // CHUNKS):
            pairs[i] = -1
            for a in range(3):
                q[a] = rot[a, 0] * src[i, 0] + rot[a, 1] * src[i, 1] + rot[a, 2] * src[i, 2] + trans[a]
            m, d2 = near[i], still_nearest(q, map_pos, near[i], searched_q[i], bound2[i], max_d2)
            if d2 < 0.0:
                m, d2, bound2[i] = nearest_bounded(q, map_pos, grid, origin, dims, voxel, radius, usable, max_d2, gaps)
                near[i] = m
                searched_q[i, :] = q
            if m < 0 or d2 > max_d2:
                continue
            out[28] += 1.0
            if not semantic_label_filter(label_filter, src_lab[i], map_lab[m]):
                continue
            out[29] += 1.0
            pairs[i] = m
            _add_pair(i, m, src, src_cov, rot, trans, map_pos, map_cov, robust_scale, out)
    return _sum_parts(parts)


@njit(cache=CACHE, nogil=True)
def gicp_linearise(
    src,
    src_cov,
    src_lab,
    rot,
    trans,
    map_pos,
    map_cov,
    map_lab,
    usable,
    grid,
    origin,
    dims,
    voxel,
    radius,
    max_dist,
    label_filter,
    robust_scale,
    pairs,
):
    """One Gauss-Newton step of GICP after a fresh search: H, g of the Mahalanobis cost, plus counts of pairs found
    and kept; the kept pairs go into `pairs` (map index per source, -1 none). The grid is padded (nearest_within)."""
    n = src.shape[0]
    near, bound2, searched_q = np.full(n, -1), np.zeros(n), np.empty((n, 3))  # nothing kept: every source searched
    args = (src, src_cov, src_lab, rot, trans, map_pos, map_cov, map_lab, usable, grid, origin, dims, voxel, radius)
    return _linearise_kept(*args, max_dist * max_dist, label_filter, robust_scale, pairs, near, bound2, searched_q)


@njit(cache=CACHE, nogil=True)
def gicp_loop(
    src,
    src_cov,
    src_lab,
    pose,
    map_pos,
    map_cov,
    map_lab,
    usable,
    grid,
    origin,
    dims,
    voxel,
    radius,
    max_dist,
    label_filter,
    robust_scale,
    iterations,
    convergence_rotation,
    convergence_translation,
    reuse_m,
    reach,
):
    """gicp's iterations from `pose`: (pose, iterations, pairs found, pairs kept, cost, information). The search is
    skipped while no source can have moved more than reuse_m since the last one; a step that converges on kept pairs
    searches once more, so that the answer's pairs are its own nearest."""
    pairs = np.empty(src.shape[0], np.int64)
    near, bound2, searched_q = np.full(src.shape[0], -1), np.zeros(src.shape[0]), np.empty((src.shape[0], 3))
    searched_at, searched_inv = pose, pose
    searched = verify = False
    found = kept = it = 0
    cost = np.inf
    information = np.zeros((6, 6))
    damping = 1e-9 * np.eye(6)
    for it in range(1, iterations + 1):  # noqa: B007 - the last `it` is the result's count
        rot, trans = pose[:3, :3].copy(), pose[:3, 3].copy()
        search = verify or not searched or moved_beyond(pose, searched_at, searched_inv, reach, reuse_m)
        if search:
            h, g, total, found, kept = _linearise_kept(
                src,
                src_cov,
                src_lab,
                rot,
                trans,
                map_pos,
                map_cov,
                map_lab,
                usable,
                grid,
                origin,
                dims,
                voxel,
                radius,
                max_dist * max_dist,
                label_filter,
                robust_scale,
                pairs,
                near,
                bound2,
                searched_q,
            )
            searched, searched_at, searched_inv = True, pose, inv(pose)
        else:
            h, g, total, _, kept = gicp_linearise_pairs(src, src_cov, rot, trans, map_pos, map_cov, pairs, robust_scale)
        if kept < 6:
            break
        cost = total / kept
        information = h
        delta = solve(h + damping, -g)
        pose = se3_exp_left(delta, pose)
        if norm(delta[:3]) < convergence_rotation and norm(delta[3:]) < convergence_translation:
            if search:
                break
            verify = True
        else:
            verify = False
    return pose, it, found, kept, cost, information
