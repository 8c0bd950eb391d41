"""A scene whose data has no stamps (the OCC-VO release: frames and a KITTI trajectory) is stamped from 1970 with one
warning line, or from --start-time; --start-time where it cannot apply is a bad argument."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from occvo_cli.cli import main


@pytest.fixture(scope="module")
def release_scene(tmp_path_factory) -> Path:
    from occvo_core.datasets.occvo_release import write_release_scene
    from occvo_core.sim import SyntheticScene

    s = SyntheticScene(seed=2, frames=4)
    return write_release_scene(tmp_path_factory.mktemp("stamps"), "four", [s[i] for i in range(4)], s.gt_poses[:4])


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if "warning" in line]


def test_no_stamps_is_said_once_and_start_time_stamps_from_then(release_scene, tmp_path, capfd):
    from occvo_core.trajectory import read_tum

    assert main(["run", "--input", str(release_scene), "--out", str(tmp_path / "a")]) == 0
    warned = _warnings(capfd.readouterr().err)
    assert warned == [
        "occvo run: warning: four has no stamps: its frames are stamped from 0 (1970-01-01) at 2 Hz; "
        "--start-time UNIX_SECONDS stamps them from then"
    ]
    np.testing.assert_array_equal(read_tum(tmp_path / "a" / "trajectory.tum")[0], [0.0, 0.5, 1.0, 1.5])

    start = 1533151603.5  # scene-0268's first sample, as nuScenes stamps it
    assert main(["run", "--input", str(release_scene), "--out", str(tmp_path / "b"), "--start-time", str(start)]) == 0
    assert _warnings(capfd.readouterr().err) == []
    for name in ("trajectory.tum", "groundtruth.tum"):
        stamps, _ = read_tum(tmp_path / "b" / name)
        np.testing.assert_allclose(stamps, start + np.arange(4) * 0.5, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(  # the stamps alone moved
        read_tum(tmp_path / "b" / "trajectory.tum")[1], read_tum(tmp_path / "a" / "trajectory.tum")[1]
    )


def test_start_time_where_it_cannot_apply_is_a_bad_argument(release_scene, tmp_path, capfd):
    from occvo_core.sim import SyntheticScene
    from occvo_core.trajectory import write_tum

    assert main(["run", "--frames", "2", "--start-time", "5", "--out", str(tmp_path / "s")]) == 2
    assert "--start-time" in capfd.readouterr().err
    gt = tmp_path / "four.tum"  # a TUM ground truth gives the frames its stamps
    write_tum(gt, SyntheticScene(seed=2, frames=4).gt_poses[:4], 100.0 + np.arange(4))
    argv = ["run", "--input", str(release_scene), "--gt", str(gt), "--out", str(tmp_path / "t")]
    assert main([*argv, "--start-time", "5"]) == 2
    assert "has its own stamps" in capfd.readouterr().err
    assert main(["run", "--input", str(release_scene), "--start-time", "nan", "--out", str(tmp_path / "n")]) == 2
    assert "finite" in capfd.readouterr().err
