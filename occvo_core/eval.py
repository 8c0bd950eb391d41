"""Trajectory evaluation as evo does it: APE of translation after SE(3) Umeyama alignment; success = RMSE < 5 m.
The paper's map metrics (Table IV) are in occvo_core.map_metrics."""

from __future__ import annotations

import numpy as np

SUCCESS_RMSE_M = 5.0  # the paper's rule


def umeyama_se3(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum |target - (R source + t)|^2 (Umeyama 1991, no scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    u, _, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    rot = u @ s @ vt
    return rot, mu_t - rot @ mu_s


def ape_errors(gt_poses: np.ndarray, est_poses: np.ndarray, align: bool = True) -> np.ndarray:
    """Per-frame translation error (m) of est against gt, after aligning est to gt."""
    gt, est = np.asarray(gt_poses), np.asarray(est_poses)
    if gt.shape != est.shape or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise ValueError(f"trajectories must be (N,4,4) of equal length, got {gt.shape} and {est.shape}")
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    if align:
        rot, trans = umeyama_se3(p_est, p_gt)
        p_est = p_est @ rot.T + trans
    return np.linalg.norm(p_gt - p_est, axis=1)


def ape_rmse(gt_poses: np.ndarray, est_poses: np.ndarray, align: bool = True) -> float:
    err = ape_errors(gt_poses, est_poses, align)
    return float(np.sqrt(np.mean(err**2)))


def success(rmse: float) -> bool:
    return bool(np.isfinite(rmse) and rmse < SUCCESS_RMSE_M)


def success_ratio(rmses) -> float:
    rmses = list(rmses)
    return sum(success(r) for r in rmses) / len(rmses) if rmses else float("nan")
