"""REP 105's frames for a run's poses: `odom` -> `base_link` continuous (never jumps), `map` -> `odom` carrying the
corrections (loop closures), and the twist of consecutive odom poses, each with a covariance in ROS's order
(x, y, z, rotation about x, y, z)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.registration.pose_covariance import skew

UNKNOWN = 1e6  # variance of what a frame does not measure (the first twist, a degenerate frame's guess)


@dataclass(frozen=True)
class FrameNames:
    map: str = "map"
    odom: str = "odom"
    base: str = "base_link"


def ros_order(cov: np.ndarray) -> np.ndarray:
    """(rotation, translation) blocks -> ROS's (translation, rotation)."""
    i = np.r_[3:6, 0:3]
    return cov[np.ix_(i, i)]


def unknown() -> np.ndarray:
    return np.eye(6) * UNKNOWN


class OdomFrames:
    """Feed each pose (map frame: the odometry's world) with its loop correction and base_link covariance."""

    def __init__(self):
        self.map_to_odom = np.eye(4)
        self._last: tuple[np.ndarray, int, np.ndarray | None] | None = None

    def update(self, pose: np.ndarray, ns: int, covariance: np.ndarray | None, loop_correction=None):
        """(odom -> base_link 4x4, its pose covariance 6x6 in odom's axes, twist (linear, angular) in base_link,
        twist covariance 6x6). A loop correction C (world -> world) moves map -> odom by C, so the odom pose
        inv(map_to_odom) @ pose goes on where the last one left off."""
        if loop_correction is not None:
            self.map_to_odom = np.asarray(loop_correction) @ self.map_to_odom
        odom = np.linalg.inv(self.map_to_odom) @ np.asarray(pose, np.float64)
        R = odom[:3, :3]
        rot = np.zeros((6, 6))
        rot[:3, :3] = rot[3:, 3:] = R
        body = unknown() if covariance is None else ros_order(covariance)
        pose_cov = rot @ body @ rot.T  # the pose's errors in odom's axes (base_link's rotated by the pose)
        linear, angular, twist_cov = np.zeros(3), np.zeros(3), unknown()
        if self._last is not None and ns > self._last[1]:
            last, last_ns, last_cov = self._last
            dt = (ns - last_ns) * 1e-9
            rel = np.linalg.inv(last) @ odom
            linear = rel[:3, :3].T @ rel[:3, 3] / dt  # the motion since the last frame, in base_link now
            angular = Rotation.from_matrix(rel[:3, :3]).as_rotvec() / dt
            if covariance is not None and last_cov is not None:
                twist_cov = twist_covariance(last_cov, covariance, rel) / dt**2
        self._last = (odom, int(ns), covariance)
        return odom, (pose_cov + pose_cov.T) / 2, (linear, angular), twist_cov


def twist_covariance(previous_cov: np.ndarray, cov: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """6x6 (ROS order) covariance of the motion rel = previous^-1 @ pose as (R^T t, rotation vector of R), from both
    poses' base_link covariances (independent registrations): for body errors (w, v) of the pose and (w', v') of
    the previous one, d(R^T t) = v + [R^T t]x w - R^T v' and d(rotation) = w - R^T w'."""
    R, u = rel[:3, :3], rel[:3, :3].T @ rel[:3, 3]
    now, before = np.zeros((6, 6)), np.zeros((6, 6))  # rows: linear, angular; columns: (w, v)
    now[:3, :3], now[:3, 3:], now[3:, :3] = skew(u), np.eye(3), np.eye(3)
    before[:3, 3:], before[3:, :3] = -R.T, -R.T
    twist = now @ cov @ now.T + before @ previous_cov @ before.T
    return (twist + twist.T) / 2
