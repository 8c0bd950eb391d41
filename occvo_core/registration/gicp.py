"""Coarse and fine GICP (the paper's Fig. 2): Generalized ICP (Segal, Haehnel, Thrun 2009) of a labelled frame
against the map around it; the semantic label filter acts on its pairs (semantic_label_filter.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occvo_core.config import GICPConfig, OccVOConfig
from occvo_core.registration.kernels.gicp_loop import gicp_loop
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


def rotation_angle(rot: np.ndarray) -> float:
    """Angle of a rotation matrix, radians."""
    return float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))


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
    """Gauss-Newton on the summed Mahalanobis distances of nearest pairs (the loop: kernels/gicp_loop.py). The
    nearest-neighbour search, most of the cost, is skipped while no point can have moved more than
    correspondence_reuse map voxels since the last one."""
    reach = float(np.sqrt((points**2).sum(axis=1).max())) if len(points) else 0.0
    origin, dims = local_map.padded_box()
    pose, it, found, kept, cost, information = gicp_loop(
        points,
        covs,
        labels.astype(np.int64),
        np.ascontiguousarray(initial_pose, dtype=np.float64),
        local_map.pos,
        local_map.cov,
        local_map.labels.astype(np.int64),
        local_map.usable if usable is None else usable,
        local_map.grid,
        origin,
        dims,
        local_map.voxel,
        max(1, int(np.ceil(max_correspondence_m / local_map.voxel))),
        max_correspondence_m,
        semantic_label_filter,
        robust_scale,
        iterations,
        convergence_rotation_rad,
        convergence_translation_m,
        correspondence_reuse * local_map.voxel,
        reach,
    )
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
