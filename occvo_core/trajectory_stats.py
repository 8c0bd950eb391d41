"""What a trajectory says about its own drift without ground truth: length, height range, pitch per 100 m.

Road scenes are nearly planar, so an estimate that climbs or tilts as it goes shows vertical drift a user should see.
"""

from __future__ import annotations

import numpy as np


def path_length(poses: np.ndarray) -> float:
    """Metres driven: the sum of the steps between consecutive positions."""
    xyz = np.asarray(poses)[:, :3, 3]
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())


def pitch_rad(poses: np.ndarray) -> np.ndarray:
    """Each pose's pitch: the angle of its forward axis (ego x) above the world's horizontal plane."""
    forward = np.asarray(poses)[:, :3, 0]
    return np.arcsin(np.clip(forward[:, 2], -1.0, 1.0))


def vertical_drift(poses: np.ndarray) -> dict[str, float]:
    """z range of the positions (m) and the pitch accumulated from the first pose to the last, per 100 m driven."""
    poses = np.asarray(poses)
    if len(poses) < 2:
        return {"z_range_m": 0.0, "pitch_deg_per_100m": 0.0}
    z = poses[:, 2, 3]
    pitch = pitch_rad(poses)
    length = path_length(poses)
    per_100m = np.degrees(pitch[-1] - pitch[0]) * 100.0 / length if length > 1.0 else 0.0
    return {"z_range_m": float(z.max() - z.min()), "pitch_deg_per_100m": float(per_100m)}
