"""Bad frames raise typed errors naming the frame and the problem; the odometry state stays as it was."""

import subprocess
import sys

import numpy as np
import pytest
from scenes import frame, town

from occvo_core import InvalidFrameError, OccupancyFrame, OccVO
from occvo_core.datasets import OccVOReleaseScene, open_scene
from occvo_core.errors import DatasetError


@pytest.fixture(scope="module")
def running():
    """An odometry that has registered two good frames."""
    pts, lab = town()
    vo = OccVO()
    vo.step(frame(pts, lab, 0))
    vo.step(frame(pts, lab, 1))
    return vo, pts, lab


def _state(vo):
    points, labels = vo.map_points()
    return vo.poses.copy(), points.copy(), labels.copy(), vo.frame_indices


def _bad_frames(pts, lab):
    nan = pts.copy()
    nan[5, 1] = np.nan
    inf = pts.copy()
    inf[7, 2] = np.inf
    outside = pts.copy()
    outside[0] = [500.0, 0.0, 0.0]
    return {
        "empty": (OccupancyFrame(np.zeros((0, 3)), np.zeros(0, np.uint8), index=7), "empty"),
        "nan": (OccupancyFrame(nan, lab, index=7), "non-finite"),
        "inf": (OccupancyFrame(inf, lab, index=7), "non-finite"),
        "shape": (OccupancyFrame(pts[:, :2], lab, index=7), "shape"),
        "labels length": (OccupancyFrame(pts, lab[:-3], index=7), "labels must have shape"),
        "label 18": (OccupancyFrame(pts, np.where(np.arange(len(lab)) == 3, 18, lab), index=7), "labels outside"),
        "label -1": (
            OccupancyFrame(pts, np.where(np.arange(len(lab)) == 3, -1, lab.astype(int)), index=7),
            "labels outside",
        ),
        "float labels": (OccupancyFrame(pts, lab.astype(float), index=7), "integers"),
        "outside grid": (OccupancyFrame(outside, lab, index=7), "outside the occupancy grid"),
    }


@pytest.mark.parametrize("case", list(_bad_frames(*town()).keys()))
def test_bad_frame_raises_typed_error_and_leaves_state_unchanged(running, case):
    vo, pts, lab = running
    bad, words = _bad_frames(pts, lab)[case]
    before = _state(vo)
    with pytest.raises(InvalidFrameError) as info:
        vo.step(bad)
    assert "frame 7" in str(info.value) and words in str(info.value)
    after = _state(vo)
    for a, b in zip(before, after):
        assert np.array_equal(a, b)
    # and the odometry goes on at the same place: within a centimetre (a fortieth of a voxel), for the voxel
    # pfilter's weighted merge of each standing frame moves map voxels, and the optimum with them, by millimetres
    r = vo.step(frame(pts, lab, 8))
    assert r.status == "ok" and np.allclose(r.pose, np.eye(4), atol=0.01)


def test_release_array_with_wrong_width_or_fractional_labels():
    with pytest.raises(InvalidFrameError, match="frame 3: expected an \\(N, 4\\) array"):
        OccupancyFrame.from_array(np.zeros((10, 3)), index=3)
    with pytest.raises(InvalidFrameError, match="whole numbers"):
        OccupancyFrame.from_array(np.array([[0.2, 0.2, 0.2, 4.5]]), index=3)


def test_unreadable_frame_file_names_the_file(tmp_path):
    scene = tmp_path / "scene-x"
    scene.mkdir()
    np.save(scene / "0.npy", np.array([[0.2, 0.2, 0.2, 11.0]]))
    (scene / "1.npy").write_bytes(b"this is not a numpy file")
    np.save(scene / "2.npy", np.array([[0.2, 0.2, np.nan, 11.0]]))
    source = OccVOReleaseScene(scene)
    assert len(source[0]) == 1
    with pytest.raises(InvalidFrameError, match=r"frame 1 .*1.npy\): unreadable occupancy frame"):
        source[1]
    with pytest.raises(InvalidFrameError, match="frame 2 .*2.npy.*non-finite"):
        source[2]


def test_frames_sort_numerically_not_as_text(tmp_path):
    scene = tmp_path / "s"
    scene.mkdir()
    for i in (0, 1, 2, 10, 11):
        np.save(scene / f"{i}.npy", np.array([[0.2 + 0.4 * i - 8, 0.2, 0.2, 11.0]]))
    source = open_scene(scene)
    assert [p.name for p in source.files] == ["0.npy", "1.npy", "2.npy", "10.npy", "11.npy"]


def test_missing_or_wrong_scene_folder_is_a_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match="no such scene folder"):
        open_scene(tmp_path / "nope")
    with pytest.raises(DatasetError, match="neither OCC-VO release frames"):
        open_scene(tmp_path)


def test_cli_prints_one_line_and_exits_non_zero_without_traceback(tmp_path):
    scene = tmp_path / "scene-bad"
    scene.mkdir()
    np.save(scene / "0.npy", np.zeros((0, 4)))
    out = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "run", "--input", str(scene), "--out", str(tmp_path / "o"), "--quiet"],
        capture_output=True,
        text=True,
    )
    assert out.returncode != 0
    assert "Traceback" not in out.stderr
    lines = [l for l in out.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and "frame 0" in lines[0] and "empty" in lines[0], out.stderr
