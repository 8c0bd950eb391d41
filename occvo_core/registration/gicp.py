"""Generalized ICP (Segal, Haehnel, Thrun 2009) of a labelled frame against a LocalMap."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.registration import kernels
from occvo_core.registration.voxel_map import LocalMap


@dataclass
class GICPResult:
    pose: np.ndarray  # 4x4, frame -> world
    iterations: int
    pairs_found: int  # nearest neighbours within the correspondence distance
    pairs_kept: int  # after the semantic label filter
    cost: float  # Mahalanobis cost per kept pair, last iteration


def se3_exp_left(delta: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """exp(delta) * pose for delta = (rotation vector, translation)."""
    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec(delta[:3]).as_matrix()
    step[:3, 3] = delta[3:]
    return step @ pose


def gicp(points: np.ndarray, covs: np.ndarray, labels: np.ndarray, local_map: LocalMap, initial_pose: np.ndarray, *,
         usable: np.ndarray | None = None,
         max_correspondence_m: float, iterations: int, semantic_label_filter: bool, robust_scale: float = 0.0,
         convergence_rotation_rad: float = 1e-5, convergence_translation_m: float = 1e-4) -> GICPResult:
    pose = np.array(initial_pose, dtype=np.float64)
    radius = max(1, int(np.ceil(max_correspondence_m / local_map.voxel)))
    found = kept = 0
    cost = np.inf
    labels = labels.astype(np.int64)
    usable = local_map.usable if usable is None else usable
    map_labels = local_map.labels.astype(np.int64)
    for it in range(1, iterations + 1):
        h, g, total, found, kept = kernels.gicp_linearise(
            points, covs, labels, pose[:3, :3].copy(), pose[:3, 3].copy(), local_map.pos, local_map.cov, map_labels,
            usable, local_map.grid, local_map.origin, local_map.dims, local_map.voxel, radius, max_correspondence_m,
            semantic_label_filter, robust_scale)
        if kept < 6:
            break
        cost = total / kept
        delta = np.linalg.solve(h + 1e-9 * np.eye(6), -g)
        pose = se3_exp_left(delta, pose)
        if np.linalg.norm(delta[:3]) < convergence_rotation_rad and np.linalg.norm(delta[3:]) < convergence_translation_m:
            break
    return GICPResult(pose, it, found, kept, cost)
