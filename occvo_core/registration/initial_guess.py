"""Initial guess (the paper's Fig. 2): the frame's pose before registration, from the motion of the last frames
(constant velocity, optionally refined by a semantic BEV correlation) or, at the second frame, from a BEV
correlation with the first (initialisation.py holds the correlations)."""

from __future__ import annotations

import numpy as np

from occvo_core.config import InitialisationConfig
from occvo_core.registration.initialisation import bev_first_motion, semantic_bev_motion
from occvo_core.registration.preprocess import Prepared


def initial_guess(
    poses: list[np.ndarray],
    prev: Prepared,
    frame: Prepared,
    config: InitialisationConfig,
    relocalised_by: np.ndarray | None = None,
) -> np.ndarray:
    """Pose guess (4x4 ego -> world) of `frame` after the frames of `poses`, the last of which was `prev`.
    relocalised_by: the loop correction that moved the last pose, if it was relocalised (its jump is no motion)."""
    if len(poses) >= 2 and config.use_constant_velocity:
        before = poses[-2] if relocalised_by is None else relocalised_by @ poses[-2]
        motion = np.linalg.inv(before) @ poses[-1]
        if config.motion_search:
            motion = semantic_bev_motion(
                prev.points,
                prev.labels,
                frame.points,
                frame.labels,
                guess=motion,
                search_radius_m=config.motion_search_radius_m,
                yaw_deg=config.motion_search_yaw_deg,
                step_deg=config.motion_search_step_deg,
                prior_sigma_m=config.motion_search_prior_m,
            )
        return poses[-1] @ motion
    motion, _ = bev_first_motion(
        prev.points,
        prev.labels,
        frame.points,
        frame.labels,
        search_radius_m=config.bev_search_radius_m,
        yaw_steps_deg=config.bev_yaw_steps_deg,
    )
    return poses[-1] @ motion
