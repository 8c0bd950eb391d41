import shutil
import subprocess

import numpy as np
import pytest
from conftest import random_pose

from occvo_core.eval import ape_rmse, success, success_ratio, umeyama_se3
from occvo_core.trajectory import read_kitti, read_trajectory, write_kitti, write_tum


def _noisy_pair(seed=0, n=60):
    rng = np.random.default_rng(seed)
    gt = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.cumsum(rng.normal(0, 0.05, n))
    gt[:, 0, 0], gt[:, 0, 1], gt[:, 1, 0], gt[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    gt[:, :3, 3] = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros(n)]) * 4.0, axis=0)
    est = random_pose(rng, 1.0, 50.0) @ gt  # a different world frame
    est[:, :3, 3] += rng.normal(0, 0.2, (n, 3))
    return gt, est


def test_umeyama_recovers_a_rigid_transform():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(100, 3)) * 10
    pose = random_pose(rng, 2.0, 20.0)
    rot, trans = umeyama_se3(src, src @ pose[:3, :3].T + pose[:3, 3])
    assert np.allclose(rot, pose[:3, :3], atol=1e-9) and np.allclose(trans, pose[:3, 3], atol=1e-9)


def test_ape_is_zero_for_a_rigidly_moved_copy_and_positive_otherwise():
    gt, est = _noisy_pair()
    moved = random_pose(np.random.default_rng(1), 1.0, 10.0) @ gt
    assert ape_rmse(gt, moved) < 1e-9
    assert 0.2 < ape_rmse(gt, est) < 0.5  # noise of 0.2 m a axis: about 0.35 m
    assert ape_rmse(gt, moved, align=False) > 1.0


def test_success_rule_is_rmse_under_5m():
    assert success(4.99) and not success(5.0) and not success(float("nan"))
    assert success_ratio([0.1, 7.0, 0.2, 0.3]) == 0.75


@pytest.mark.skipif(shutil.which("evo_ape") is None, reason="evo is a dev dependency: pip install -e .[dev]")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ape_equals_evo_ape_kitti_aligned(tmp_path, seed):
    gt, est = _noisy_pair(seed)
    write_kitti(tmp_path / "gt.kitti", gt)
    write_kitti(tmp_path / "est.kitti", est)
    out = subprocess.run(
        ["evo_ape", "kitti", str(tmp_path / "gt.kitti"), str(tmp_path / "est.kitti"), "-a"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    evo_rmse = float(next(line.split()[1] for line in out.splitlines() if line.strip().startswith("rmse")))
    ours = ape_rmse(read_kitti(tmp_path / "gt.kitti"), read_kitti(tmp_path / "est.kitti"))
    assert abs(ours - evo_rmse) <= 1e-4


def test_trajectory_round_trip_kitti_and_tum(tmp_path):
    gt, _ = _noisy_pair()
    write_kitti(tmp_path / "a.kitti", gt)
    write_tum(tmp_path / "a.tum", gt)
    assert np.allclose(read_trajectory(tmp_path / "a.kitti"), gt, atol=1e-8)
    assert np.allclose(read_trajectory(tmp_path / "a.tum"), gt, atol=1e-8)
