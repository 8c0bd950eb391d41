"""Coarse and fine GICP (the paper's Fig. 2): Generalized ICP (Segal, Haehnel, Thrun 2009) of a labelled frame
against the map around it; the semantic label filter acts on its pairs (semantic_label_filter.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from occvo_core.config import GICPConfig, OccVOConfig
from occvo_core.registration.kernels.gicp import gicp_linearise, gicp_linearise_pairs
from occvo_core.registration.local_map import EgoMap, LocalMap
from occvo_core.registration.preprocess import Prepared


@dataclass
class GICPResult:
    pose: np.ndarray  # 4x4, frame -> world
    iterations: int
    pairs_found: int  # nearest neighbours within the correspondence distance
    pairs_kept: int  # after the semantic label filter
    cost: float  # Mahalanobis cost per kept pair, last iteration
    # J^T W J of the last Gauss-Newton step (6x6, rotation vector then translation, perturbing the pose on the left,
    # in the map's coordinates): the information of the answer; zeros when no step was taken
    information: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


def rotvec_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation.from_rotvec(rotvec).as_matrix(), bit for bit (scipy's quaternion formulas, in its operation order),
    without scipy's per-call cost, which was a fair share of a GICP iteration."""
    x, y, z = float(rotvec[0]), float(rotvec[1]), float(rotvec[2])
    angle = math.sqrt(x * x + y * y + z * z)
    if angle <= 1e-3:  # scipy's Taylor series of sin(angle / 2) / angle
        a2 = angle * angle
        scale = 0.5 - a2 / 48 + a2 * a2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    qx, qy, qz, qw = scale * x, scale * y, scale * z, math.cos(angle / 2)
    x2, y2, z2, w2 = qx * qx, qy * qy, qz * qz, qw * qw
    xy, zw, xz, yw, yz, xw = qx * qy, qz * qw, qx * qz, qy * qw, qy * qz, qx * qw
    return np.array(
        [
            [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
            [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
            [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2],
        ]
    )


def se3_exp_left(delta: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """exp(delta) * pose for delta = (rotation vector, translation)."""
    step = np.eye(4)
    step[:3, :3] = rotvec_matrix(delta[:3])
    step[:3, 3] = delta[3:]
    return step @ pose


def rotation_angle(rot: np.ndarray) -> float:
    """Angle of a rotation matrix, radians."""
    return float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))


def _moved(pose: np.ndarray, since: np.ndarray, reach: float, since_inv: np.ndarray | None = None) -> float:
    """Bound on how far any point within `reach` of the origin moved from pose `since` to `pose` (since_inv: its
    inverse, when the caller keeps it)."""
    step = pose @ (np.linalg.inv(since) if since_inv is None else since_inv)
    return float(np.linalg.norm(step[:3, 3]) + rotation_angle(step[:3, :3]) * (reach + np.linalg.norm(since[:3, 3])))


def gicp(
    points: np.ndarray,
    covs: np.ndarray,
    labels: np.ndarray,
    local_map: LocalMap | EgoMap,
    initial_pose: np.ndarray,
    *,
    usable: np.ndarray | None = None,
    max_correspondence_m: float,
    iterations: int,
    semantic_label_filter: bool,
    robust_scale: float = 0.0,
    convergence_rotation_rad: float = 1e-5,
    convergence_translation_m: float = 1e-4,
    correspondence_reuse: float = 0.0,
) -> GICPResult:
    """Gauss-Newton on the summed Mahalanobis distances of nearest pairs. The nearest-neighbour search, most of the
    cost, is skipped while no point can have moved more than correspondence_reuse map voxels since the last one."""
    pose = np.array(initial_pose, dtype=np.float64)
    reach = float(np.sqrt((points**2).sum(axis=1).max())) if len(points) else 0.0
    pairs = np.empty(len(points), np.int64)
    searched_at = None
    radius = max(1, int(np.ceil(max_correspondence_m / local_map.voxel)))
    found = kept = 0
    cost = np.inf
    labels = labels.astype(np.int64)
    usable = local_map.usable if usable is None else usable
    map_labels = local_map.labels.astype(np.int64)
    origin, dims = local_map.padded_box()
    verify = False
    information = np.zeros((6, 6))
    damping = 1e-9 * np.eye(6)
    searched_inv = None  # the inverse of searched_at, taken once a search
    for it in range(1, iterations + 1):  # noqa: B007 - the last `it` is the result's count
        rot, trans = pose[:3, :3].copy(), pose[:3, 3].copy()
        search = (
            verify
            or searched_at is None
            or _moved(pose, searched_at, reach, searched_inv) > correspondence_reuse * local_map.voxel
        )
        if search:
            h, g, total, found, kept = gicp_linearise(
                points,
                covs,
                labels,
                rot,
                trans,
                local_map.pos,
                local_map.cov,
                map_labels,
                usable,
                local_map.grid,
                origin,
                dims,
                local_map.voxel,
                radius,
                max_correspondence_m,
                semantic_label_filter,
                robust_scale,
                pairs,
            )
            searched_at, searched_inv = pose, np.linalg.inv(pose)
        else:
            h, g, total, _, kept = gicp_linearise_pairs(
                points, covs, rot, trans, local_map.pos, local_map.cov, pairs, robust_scale
            )
        if kept < 6:
            break
        cost = total / kept
        information = h  # a new array each step
        delta = np.linalg.solve(h + damping, -g)
        pose = se3_exp_left(delta, pose)
        if (
            np.linalg.norm(delta[:3]) < convergence_rotation_rad
            and np.linalg.norm(delta[3:]) < convergence_translation_m
        ):
            if search:
                break
            verify = True  # converged on kept pairs: search once more, so the answer's pairs are its own nearest
        else:
            verify = False
    return GICPResult(pose, it, found, kept, cost, information)


def register_sources(
    frame: Prepared,
    sources: np.ndarray,
    local_map: LocalMap | EgoMap,
    pose: np.ndarray,
    max_correspondence_m: float,
    iterations: int,
    config: OccVOConfig,
) -> GICPResult:
    """GICP of the frame's points `sources` from `pose`, with the config's solver settings and label filter."""
    g: GICPConfig = config.gicp
    return gicp(
        frame.points[sources],
        frame.covs[sources],
        frame.labels[sources],
        local_map,
        pose,
        max_correspondence_m=max_correspondence_m,
        iterations=iterations,
        robust_scale=g.robust_kernel_scale,
        semantic_label_filter=config.semantic_label_filter.enabled,
        convergence_rotation_rad=g.convergence_rotation_rad,
        convergence_translation_m=g.convergence_translation_m,
        correspondence_reuse=g.correspondence_reuse,
    )


def coarse_gicp(frame: Prepared, ego: EgoMap, config: OccVOConfig) -> GICPResult:
    """Coarse GICP against the map pooled on a coarse grid. A wide pass first (the map pooled wider still) reaches
    minima metres away; when it lands far from the guess, both starts are refined and the one whose alignment keeps
    clearly more pairs wins, since repeated structure (tree rows, lamp posts) can give the wide pass a wrong one."""
    cfg = config.gicp
    coarse_map = ego.pooled(cfg.coarse_map_voxel_m)
    starts = [np.eye(4)]
    if cfg.wide_voxel_m > 0:
        wide = register_sources(
            frame,
            frame.wide,
            coarse_map.pooled(cfg.wide_voxel_m),
            np.eye(4),
            cfg.wide_voxel_m,
            cfg.coarse_iterations,
            config,
        ).pose
        # a wide pass that barely moved the guess leads coarse GICP to the minimum the guess would; one that moved
        # it further may lead it on into a neighbouring one
        near = np.linalg.norm(wide[:3, 3]) < cfg.wide_trust_m and rotation_angle(wide[:3, :3]) < np.deg2rad(2.0)
        starts = [wide] if near else [np.eye(4), wide]
    results = [
        register_sources(
            frame, frame.coarse, coarse_map, start, cfg.coarse_max_correspondence_m, cfg.coarse_iterations, config
        )
        for start in starts
    ]
    if len(results) == 1:
        return results[0]
    from_guess, from_wide = results
    # the guess is the prior: the wide pass's minimum must be clearly better supported to replace it
    return from_wide if from_wide.pairs_kept > (1 + cfg.wide_pairs_margin) * from_guess.pairs_kept else from_guess


def fine_gicp(frame: Prepared, sources: np.ndarray, ego: EgoMap, start: np.ndarray, config: OccVOConfig) -> GICPResult:
    """Fine GICP of the frame's sources (the dynamic object filter's kept ones) against the unpooled map."""
    g = config.gicp
    return register_sources(frame, sources, ego, start, g.fine_max_correspondence_m, g.fine_iterations, config)
