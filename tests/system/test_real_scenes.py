"""End to end on the real nuScenes sample (skipped where ../shared is absent): the CLI, its outputs, the bounds."""

import json
import subprocess
import sys

import numpy as np
import pytest

from occvo_core.eval import ape_rmse
from occvo_core.io import read_map
from occvo_core.trajectory import read_kitti, read_tum

# The release's frames lie ~50 and ~100 ms after their poses (benchmarks/accuracy.py), so plain APE is bounded by
# the data (0.22 and 0.40 m measured, docs/results.md, Accuracy) and the APE at the best time shift says how good the
# odometry is (0.07 and 0.10 m). The bounds catch regressions from the current figures.
RMSE_BOUND_M = {"scene-0101": 0.30, "scene-0268": 0.45}
TIME_FITTED_BOUND_M = 0.12


@pytest.mark.parametrize("scene", ["scene-0101", "scene-0268"])
def test_occvo_run_on_real_scene_writes_everything_and_meets_its_bound(sample_root, tmp_path, scene):
    out = tmp_path / "out"
    gt = sample_root / "trajectory" / f"{scene}.kitti"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "occvo_cli",
            "run",
            "--input",
            str(sample_root / "occupancy" / scene),
            "--gt",
            str(gt),
            "--out",
            str(out),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == len(read_kitti(gt))
    assert summary["success"] is True
    assert summary["ape_rmse_m"] <= RMSE_BOUND_M[scene]
    assert summary["ape_rmse_time_fitted_m"] <= TIME_FITTED_BOUND_M and abs(summary["time_offset_ms"]) <= 250
    assert set(summary["ms_per_stage_median"]) >= {
        "preprocess",
        "coarse_gicp",
        "dynamic_object_filter",
        "fine_gicp",
        "voxel_pfilter",
    }
    est = read_kitti(out / "trajectory.kitti")
    assert np.allclose(read_tum(out / "trajectory.tum")[1], est, atol=1e-6)
    assert abs(ape_rmse(read_kitti(gt), est) - summary["ape_rmse_m"]) < 1e-6
    pts_npz, lab_npz = read_map(out / "map.npz")
    pts_ply, lab_ply = read_map(out / "map.ply")
    assert len(pts_npz) > 50_000 and np.array_equal(lab_npz, lab_ply) and np.allclose(pts_npz, pts_ply, atol=1e-4)
    assert (out / "trajectory.png").stat().st_size > 10_000
    evals = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "eval", "--gt", str(gt), "--est", str(out / "trajectory.kitti"), "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert abs(json.loads(evals.stdout)["rmse"] - summary["ape_rmse_m"]) < 1e-6


def test_fast_start_of_scene_0268_is_found_without_ground_truth(sample_root):
    """OccVO.step sees frames only; the BEV initialisation must find the 4.8 m first motion by itself."""
    from occvo_core import OccVO
    from occvo_core.datasets import OccVOReleaseScene

    source = OccVOReleaseScene(sample_root / "occupancy" / "scene-0268")
    vo = OccVO()
    for i in range(4):
        vo.step(source[i])
    gt = source.gt_poses
    for i in range(1, 4):
        true_step = np.linalg.inv(gt[i - 1]) @ gt[i]
        est_step = np.linalg.inv(vo.poses[i - 1]) @ vo.poses[i]
        assert np.linalg.norm(true_step[:3, 3]) > 4.0
        assert np.linalg.norm(est_step[:3, 3] - true_step[:3, 3]) < 0.15


def test_a_wide_pass_that_moved_the_guess_does_not_lead_coarse_gicp_into_a_neighbouring_minimum(sample_root):
    """scene-0101 with every frame turned 180 degrees about z (the same road, driven with the sensors facing back):
    at frame 18 the wide pass moved the good constant-velocity guess 0.98 m, and coarse GICP from there alone went on
    2.8 m along the road; started from the guess too, the alignment keeping more pairs is the right one."""
    from occvo_core import OccVO
    from occvo_core.datasets import OccVOReleaseScene
    from occvo_core.frame import OccupancyFrame

    source = OccVOReleaseScene(sample_root / "occupancy" / "scene-0101")
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    gt = turn @ source.gt_poses @ turn  # the turned ego's poses
    vo = OccVO()
    for i in range(20):
        frame = source[i]
        vo.step(OccupancyFrame(frame.points * [-1.0, -1.0, 1.0], frame.labels, frame.index))
    for i in range(15, 20):
        true_step = np.linalg.inv(gt[i - 1]) @ gt[i]
        est_step = np.linalg.inv(vo.poses[i - 1]) @ vo.poses[i]
        assert np.linalg.norm(est_step[:3, 3] - true_step[:3, 3]) < 0.3, (i, est_step[:3, 3], true_step[:3, 3])
