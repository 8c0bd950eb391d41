"""Time-offset-aware APE: how much of a trajectory's error is timing.

A camera frame stamped a few tens of ms away from the pose it is paired with puts every estimate that far along the
track. The fit moves the ground truth in time by one shift dt (SE(3) interpolation between its poses: translation
on the constant twist between two poses) and keeps the dt with the smallest APE. dt > 0: the estimate at stamp s matches the ground
truth at s + dt (the frames were taken after their poses' stamps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.eval import ape_rmse

MAX_OFFSET_MS = 250.0


@dataclass(frozen=True)
class TimeFit:
    ape_rmse_m: float  # APE against the ground truth moved by offset_ms, after SE(3) alignment
    offset_ms: float
    dropped_frames: int  # estimates whose shifted stamp falls outside the ground truth


def _skew(w: np.ndarray) -> np.ndarray:
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    return out - np.swapaxes(out, -1, -2)


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """V(w) of SE(3)'s exponential: translation = V(w) u for the twist (w, u)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = _skew(w)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a * k + b * (k @ k)


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses at query stamps (inside [stamps[0], stamps[-1]]) on SE(3): between two poses the constant twist that
    joins them (a car in a steady turn follows its arc, not the chord)."""
    i = np.clip(np.searchsorted(stamps, query, side="right") - 1, 0, len(stamps) - 2)
    s = ((query - stamps[i]) / (stamps[i + 1] - stamps[i]))[:, None]
    rel = np.linalg.inv(poses[i]) @ poses[i + 1]
    w = Rotation.from_matrix(rel[:, :3, :3]).as_rotvec()
    u = np.linalg.solve(_left_jacobian(w), rel[:, :3, 3:])[..., 0]
    step = np.tile(np.eye(4), (len(query), 1, 1))
    step[:, :3, :3] = Rotation.from_rotvec(s * w).as_matrix()
    step[:, :3, 3] = (_left_jacobian(s * w) @ (s * u)[..., None])[..., 0]
    return poses[i] @ step


def fit_time_offset(
    gt: np.ndarray, est: np.ndarray, stamps: np.ndarray, max_offset_ms: float = MAX_OFFSET_MS, step_ms: float = 1.0
) -> TimeFit:
    """The shift of the ground truth in time (within +-max_offset_ms) that best explains est; gt and est are (N,4,4)
    at the same stamps (seconds, increasing). The shift is chosen on the frames that stay inside the ground truth at
    every shift searched, so that dropping an end frame cannot make a shift look better."""
    gt, est, stamps = np.asarray(gt, np.float64), np.asarray(est, np.float64), np.asarray(stamps, np.float64)
    if gt.shape != est.shape or len(stamps) != len(gt) or len(gt) < 3:
        raise ValueError(f"need three or more poses at matching stamps, got {gt.shape}, {est.shape}, {stamps.shape}")
    if np.any(np.diff(stamps) <= 0):
        raise ValueError("stamps must increase")
    reach = max_offset_ms / 1e3
    common = (stamps - reach >= stamps[0]) & (stamps + reach <= stamps[-1])
    if common.sum() < 3:
        common = np.ones(len(stamps), bool)  # too short for a common set: judged on every frame inside
    shifts = np.arange(-max_offset_ms, max_offset_ms + 0.5 * step_ms, step_ms)
    best, best_ape = 0.0, np.inf
    for dt in shifts:
        q = stamps + dt / 1e3
        use = common & (q >= stamps[0]) & (q <= stamps[-1])
        ape = ape_rmse(interpolate_poses(stamps, gt, q[use]), est[use])
        if ape < best_ape:
            best, best_ape = float(dt), ape
    q = stamps + best / 1e3
    inside = (q >= stamps[0]) & (q <= stamps[-1])
    ape = ape_rmse(interpolate_poses(stamps, gt, q[inside]), est[inside])
    return TimeFit(ape, best, int((~inside).sum()))
