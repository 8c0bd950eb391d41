"""`occvo eval` on TUM files with different stamps and counts associates them as evo does (the nearest stamp within
--t-max-diff) and gives evo's APE and RPE, translation and rotation angle (evo's -r angle_deg), to 1e-6; KITTI files
still pair pose by pose."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from occvo_cli.cli import main

pytest.importorskip("evo", reason="evo is in the dev extra")
from test_evo_outputs import STATS, _evo, _occvo_eval  # noqa: E402 - evo's command line, as the run's outputs test runs it

START = 1533151603.5  # a real nuScenes stamp: association must hold at Unix-time magnitudes


def _drive(gaps_in: str, tmp_path) -> tuple[str, str]:
    """Ground truth of a synthetic drive at 2 Hz and a noisy, rigidly moved estimate of it, as TUM files: the
    estimate's stamps jittered by up to 6 ms, with extra poses between frames that match nothing, and every 7th frame
    missing from one of the two."""
    from occvo_core.sim import SyntheticScene
    from occvo_core.trajectory import write_tum

    rng = np.random.default_rng(7)
    gt = SyntheticScene(seed=3, frames=40).gt_poses
    stamps = START + 0.5 * np.arange(len(gt))
    moved = np.eye(4)
    moved[:3, :3], moved[:3, 3] = Rotation.from_euler("z", 30, degrees=True).as_matrix(), [5.0, -2.0, 0.3]
    est = moved @ gt
    est[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (len(gt), 3))).as_matrix() @ est[:, :3, :3]
    est[:, :3, 3] += rng.normal(0, 0.1, (len(gt), 3))
    est_stamps = stamps + rng.uniform(-0.006, 0.006, len(gt))
    keep = np.arange(len(gt)) % 7 != 3
    extra = est[5:8].copy(), stamps[5:8] + 0.25  # a quarter-second off any ground-truth stamp
    if gaps_in == "est":
        est, est_stamps = est[keep], est_stamps[keep]
    else:
        gt, stamps = gt[keep], stamps[keep]
    order = np.argsort(np.concatenate([est_stamps, extra[1]]))
    write_tum(tmp_path / "gt.tum", gt, stamps)
    write_tum(
        tmp_path / "est.tum", np.concatenate([est, extra[0]])[order], np.concatenate([est_stamps, extra[1]])[order]
    )
    return str(tmp_path / "gt.tum"), str(tmp_path / "est.tum")


CASES = [
    ("ape", [], ["-a"]),
    ("ape", ["--t-max-diff", "0.003"], ["-a", "--t_max_diff", "0.003"]),
    ("rpe", ["--rpe"], []),
    ("rpe", ["--rpe", "--delta", "2", "--t-max-diff", "0.004"], ["--delta", "2", "--t_max_diff", "0.004"]),
]


@pytest.mark.parametrize("gaps_in", ["est", "gt"])
@pytest.mark.parametrize("tool,flags,evo_flags", CASES)
def test_evo_agrees_on_associated_stamps(tmp_path, capsys, gaps_in, tool, flags, evo_flags):
    gt, est = _drive(gaps_in, tmp_path)
    ours = _occvo_eval(capsys, "--gt", gt, "--est", est, *flags)
    theirs = _evo(tool, "tum", gt, est, *evo_flags)
    theirs_deg = _evo(tool, "tum", gt, est, *evo_flags, "-r", "angle_deg")
    for k in STATS:
        assert ours[k] == pytest.approx(theirs[k], abs=1e-6), k
        assert ours["rotation_deg"][k] == pytest.approx(theirs_deg[k], abs=1e-6), k
    assert ours["rotation_deg"]["rmse"] > 0.1  # the noise is there to be measured


def test_kitti_files_pair_by_index_and_need_as_many_poses(tmp_path, capsys):
    from occvo_core.trajectory import read_tum, write_kitti, write_tum

    gt, est = _drive("est", tmp_path)
    write_kitti(tmp_path / "gt.kitti", read_tum(gt)[1])
    write_kitti(tmp_path / "est.kitti", read_tum(est)[1])
    assert main(["eval", "--gt", str(tmp_path / "gt.kitti"), "--est", str(tmp_path / "est.kitti")]) == 2
    assert "no stamps to associate by" in capsys.readouterr().err
    stamps, poses = read_tum(gt)
    far = tmp_path / "far.tum"  # an hour later: nothing to associate
    write_tum(far, poses, stamps + 3600.0)
    assert main(["eval", "--gt", gt, "--est", str(far)]) == 2
    assert "no stamp within --t-max-diff 0.01 s" in capsys.readouterr().err
