"""Trajectory evaluation as evo does it: APE of translation after SE(3) Umeyama alignment; success = RMSE < 5 m.
The paper's map metrics (Table IV) are in occvo_core.map_metrics."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

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


def _paired(gt_poses: np.ndarray, est_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt, est = np.asarray(gt_poses), np.asarray(est_poses)
    if gt.shape != est.shape or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise ValueError(f"trajectories must be (N,4,4) of equal length, got {gt.shape} and {est.shape}")
    return gt, est


def ape_errors(gt_poses: np.ndarray, est_poses: np.ndarray, align: bool = True) -> np.ndarray:
    """Per-frame translation error (m) of est against gt, after aligning est to gt."""
    gt, est = _paired(gt_poses, est_poses)
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    if align:
        rot, trans = umeyama_se3(p_est, p_gt)
        p_est = p_est @ rot.T + trans
    return np.linalg.norm(p_gt - p_est, axis=1)


def ape_rotation_errors_deg(gt_poses: np.ndarray, est_poses: np.ndarray, align: bool = True) -> np.ndarray:
    """Per-frame rotation error (degrees) of est against gt after the alignment of ape_errors: evo_ape -r angle_deg."""
    gt, est = _paired(gt_poses, est_poses)
    rot = umeyama_se3(est[:, :3, 3], gt[:, :3, 3])[0] if align else np.eye(3)
    return _angles_deg(np.swapaxes(gt[:, :3, :3], 1, 2) @ rot @ est[:, :3, :3])


def _angles_deg(rotations: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(rotations).magnitude())


def ape_rmse(gt_poses: np.ndarray, est_poses: np.ndarray, align: bool = True) -> float:
    err = ape_errors(gt_poses, est_poses, align)
    return float(np.sqrt(np.mean(err**2)))


def project_to_plane(poses: np.ndarray) -> np.ndarray:
    """Poses with their height dropped (z = 0), as `evo_ape --project_to_plane xy`: for ground truth that lies on a
    map's plane whatever the road's slope (nuScenes' ego poses: z = 0 up a ramp), against which a 3D estimate's true
    climb would count as error."""
    out = np.array(poses, np.float64, copy=True)
    out[:, 2, 3] = 0.0
    return out


def success(rmse: float) -> bool:
    return bool(np.isfinite(rmse) and rmse < SUCCESS_RMSE_M)


def success_ratio(rmses) -> float:
    rmses = list(rmses)
    return sum(success(r) for r in rmses) / len(rmses) if rmses else float("nan")


def rpe_pairs(poses: np.ndarray, delta: float = 1, unit: str = "f") -> list[tuple[int, int]]:
    """The pose pairs evo's RPE compares (consecutive pairs, chosen on the estimate as evo does by default): every
    delta-th frame (unit "f"), or the next pose once delta metres of path have been driven since the last (unit "m")."""
    poses = np.asarray(poses)
    if delta <= 0:
        raise ValueError(f"delta must be more than 0, not {delta}")
    if unit == "f":
        if float(delta) != int(delta):
            raise ValueError(f"delta in frames must be a whole number, not {delta}")
        ids = list(range(0, len(poses), int(delta)))
    elif unit == "m":
        ids, path = [0], 0.0
        for i in range(1, len(poses)):
            path += float(np.linalg.norm(poses[i, :3, 3] - poses[i - 1, :3, 3]))
            if path >= delta:
                ids.append(i)
                path = 0.0
    else:
        raise ValueError(f"delta unit is f (frames) or m (metres), not {unit!r}")
    pairs = list(zip(ids, ids[1:]))
    if not pairs:
        raise ValueError(f"delta {delta} {unit} leaves no pair of poses in {len(poses)}")
    return pairs


def rpe_errors(gt_poses: np.ndarray, est_poses: np.ndarray, delta: float = 1, unit: str = "f") -> np.ndarray:
    """Per pair (i, j) the translation of (gt_i^-1 gt_j)^-1 (est_i^-1 est_j): evo_rpe's translation part. Relative
    motions do not change under a rigid alignment, so no alignment is needed."""
    gt, est = _paired(gt_poses, est_poses)
    return np.linalg.norm(_relative_errors(gt, est, delta, unit)[:, :3, 3], axis=1)


def rpe_rotation_errors_deg(
    gt_poses: np.ndarray, est_poses: np.ndarray, delta: float = 1, unit: str = "f"
) -> np.ndarray:
    """The rotation angle (degrees) of the same relative errors: evo_rpe -r angle_deg."""
    gt, est = _paired(gt_poses, est_poses)
    return _angles_deg(_relative_errors(gt, est, delta, unit)[:, :3, :3])


def _relative_errors(gt: np.ndarray, est: np.ndarray, delta: float, unit: str) -> np.ndarray:
    """(gt_i^-1 gt_j)^-1 (est_i^-1 est_j) for each pair of rpe_pairs."""
    i, j = np.array(rpe_pairs(est, delta, unit)).T
    rel_gt = np.linalg.inv(gt[i]) @ gt[j]
    rel_est = np.linalg.inv(est[i]) @ est[j]
    return np.linalg.inv(rel_gt) @ rel_est
