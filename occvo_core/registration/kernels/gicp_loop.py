"""GICP's Gauss-Newton loop compiled whole: search, linearise, solve, step and convergence test without a return to
Python between iterations (each return cost more than the search of a coarse pass)."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.gicp import gicp_linearise, gicp_linearise_pairs
from occvo_core.registration.kernels.numpy_blas import inv, norm, solve
from occvo_core.registration.kernels.se3 import moved_beyond, se3_exp_left


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
            h, g, total, found, kept = gicp_linearise(
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
