"""The covariance of a registered pose from fine GICP's information matrix (J^T W J of its last Gauss-Newton step),
and of the motion between two registered poses.

Fine GICP solves for a left perturbation delta = (rotation vector, translation) of the frame's pose in the predicted
ego frame (pose = guess @ exp(delta) @ F); the inverse information is delta's covariance. Moved to the right of the
pose (pose @ exp(eps), eps = Ad(F^-1) delta) it is the covariance in base_link, the frame ROS consumers perturb.

Each frame is registered to the map on its own, so the motion from frame i-1 to frame i carries both frames'
errors: its covariance sums both (relative_translation_covariance). So computed, the inverse information needs no
scale: the mean NEES of the relative translations against the exact ground truth of synthetic seeds 100-119 lies
in chi-square's 95% interval (benchmarks/covariance_nees.py; docs/design.md says how it is computed)."""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def adjoint(T: np.ndarray) -> np.ndarray:
    """Ad(T) on (rotation, translation) twists: exp(Ad(T) x) = T exp(x) T^-1."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = skew(t) @ R
    return A


def pose_covariance(information: np.ndarray, fine_pose: np.ndarray) -> np.ndarray | None:
    """6x6 covariance of the pose in base_link, (rotation x, y, z, translation x, y, z); None when fine GICP's
    information does not fix all six directions."""
    info = np.asarray(information, np.float64)
    if not np.all(np.isfinite(info)) or not _full_rank(info):
        return None
    A = adjoint(np.linalg.inv(fine_pose))
    cov = A @ np.linalg.inv(info) @ A.T
    return (cov + cov.T) / 2


def _full_rank(info: np.ndarray) -> bool:
    """np.linalg.matrix_rank(info) == 6, its SVD skipped where the condition number, bounded by the product of the
    Frobenius norms of info and its inverse, lies many orders below the rank's tolerance (1 / (6 eps))."""
    try:
        bound = np.linalg.norm(info) * np.linalg.norm(np.linalg.inv(info))
    except np.linalg.LinAlgError:
        bound = np.inf
    return bool(bound < 1e10) or np.linalg.matrix_rank(info) == 6


def relative_translation_covariance(
    previous_cov: np.ndarray, cov: np.ndarray, previous: np.ndarray, pose: np.ndarray
) -> np.ndarray:
    """3x3 covariance of the translation t of previous^-1 @ pose (in previous's frame), from both poses' covariances
    in base_link (independent registrations): dt = R v - v' + [t]x w' for body errors (w, v) of pose and (w', v') of
    previous."""
    rel = np.linalg.inv(previous) @ pose
    R, t = rel[:3, :3], rel[:3, 3]
    J = np.hstack([skew(t), -np.eye(3)])
    return R @ cov[3:, 3:] @ R.T + J @ previous_cov @ J.T


def relative_translation_nees(gt: np.ndarray, poses: np.ndarray, covs: list) -> np.ndarray:
    """For each frame i >= 1 where both covariances are known: e^T C^-1 e, e = the translation of
    poses[i-1]^-1 poses[i] minus the ground truth's, C its covariance. Chi-square with 3 degrees of freedom when the
    covariances are calibrated."""
    out = []
    for i in range(1, len(poses)):
        if covs[i] is None or covs[i - 1] is None:
            continue
        est = np.linalg.inv(poses[i - 1]) @ poses[i]
        truth = np.linalg.inv(gt[i - 1]) @ gt[i]
        e = est[:3, 3] - truth[:3, 3]
        C = relative_translation_covariance(covs[i - 1], covs[i], poses[i - 1], poses[i])
        out.append(float(e @ np.linalg.solve(C, e)))
    return np.array(out)
