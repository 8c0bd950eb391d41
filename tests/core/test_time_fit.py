"""Time-offset-aware APE: a known shift between estimate and ground truth comes back, and so does the APE."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from occvo_core.eval import ape_rmse
from occvo_core.time_fit import fit_time_offset, interpolate_poses
from occvo_core.trajectory_stats import path_length, vertical_drift


def drive(t: np.ndarray) -> np.ndarray:
    """A car that speeds up through a bend: poses at times t (seconds)."""
    s = 2.0 * t + 0.3 * t**2  # metres along the path
    yaw = 0.03 * s
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, 0, 3] = np.sin(yaw) / 0.03
    poses[:, 1, 3] = (1 - np.cos(yaw)) / 0.03
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    return poses


@pytest.mark.parametrize("offset_ms", [-140.0, 0.0, 73.0, 210.0])
def test_a_known_time_shift_is_recovered_within_10_ms(offset_ms):
    stamps = np.arange(40) / 2.0
    gt = drive(stamps)
    rng = np.random.default_rng(1)
    est = drive(stamps + offset_ms / 1e3)  # frames taken offset_ms after their poses' stamps
    est[:, :3, 3] += rng.normal(0, 0.01, (40, 3))
    fit = fit_time_offset(gt, est, stamps)
    assert abs(fit.offset_ms - offset_ms) <= 10.0
    assert fit.ape_rmse_m < 0.05 < ape_rmse(gt, est) or offset_ms == 0.0
    assert fit.dropped_frames == (abs(fit.offset_ms) > 0)  # one end falls outside the ground truth


def test_interpolation_between_poses_follows_the_arc_of_a_steady_turn():
    """A quarter circle of radius 10 m between two poses: half-way the car is on the arc, heading 45 degrees."""
    stamps = np.array([0.0, 1.0])
    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    b[:3, 3] = [10.0, 10.0, 0.0]
    mid = interpolate_poses(stamps, np.stack([a, b]), np.array([0.5]))[0]
    assert np.allclose(mid[:3, 3], [10 * np.sin(np.pi / 4), 10 * (1 - np.cos(np.pi / 4)), 0.0])
    assert np.isclose(Rotation.from_matrix(mid[:3, :3]).as_euler("zyx", degrees=True)[0], 45.0)


def test_bad_input_is_refused():
    stamps = np.arange(5) / 2.0
    with pytest.raises(ValueError, match="stamps must increase"):
        fit_time_offset(drive(stamps), drive(stamps), stamps[::-1])
    with pytest.raises(ValueError, match="three or more"):
        fit_time_offset(drive(stamps[:2]), drive(stamps[:2]), stamps[:2])


def test_vertical_drift_reports_a_climb_and_a_tilt():
    stamps = np.arange(21) / 2.0
    flat = drive(stamps)
    assert vertical_drift(flat) == {"z_range_m": 0.0, "pitch_deg_per_100m": 0.0}
    climbing = flat.copy()
    climbing[:, 2, 3] = np.linspace(0, 1.5, 21)
    tilt = np.radians(np.linspace(0, 2.0, 21))  # nose up by 2 degrees over the drive
    climbing[:, :3, :3] = climbing[:, :3, :3] @ Rotation.from_euler("y", -tilt[:, None]).as_matrix()
    drift = vertical_drift(climbing)
    assert np.isclose(drift["z_range_m"], 1.5)
    assert np.isclose(drift["pitch_deg_per_100m"], 2.0 * 100 / path_length(climbing), rtol=1e-6)


def test_occvo_eval_fits_the_time_offset_of_two_trajectory_files(tmp_path):
    import json
    import subprocess
    import sys

    from occvo_core.trajectory import write_kitti, write_tum

    stamps = 100.0 + np.arange(40) / 2.0
    write_tum(tmp_path / "gt.tum", drive(stamps - 100.0), stamps)
    write_kitti(tmp_path / "est.kitti", drive(stamps - 100.0 + 0.06))
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "occvo_cli",
            "eval",
            "--gt",
            str(tmp_path / "gt.tum"),
            "--est",
            str(tmp_path / "est.kitti"),
            "--fit-time-offset",
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    stats = json.loads(out.stdout)
    assert abs(stats["time_offset_ms"] - 60.0) <= 10.0 and stats["ape_rmse_time_fitted_m"] < 0.01 < stats["rmse"]
