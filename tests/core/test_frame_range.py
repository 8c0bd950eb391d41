"""Part of a scene as a scene of its own: frame 0 is the first kept, ground truth and stamps sliced to match, the
source's other attributes passed through, and `occvo run --keyframes` refused on anything but a nuScenes drive."""

import numpy as np
import pytest

from occvo_core.datasets.frame_range import FrameRange
from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame


class _Scene:
    name, rate_hz, predictor = "made-up", 2.0, "the source's own"

    def __init__(self, n):
        self.gt_poses = np.array([np.eye(4) + i for i in range(n)])
        self.stamps = np.arange(n) * 0.5 + 100

    def __len__(self):
        return len(self.gt_poses)

    def __getitem__(self, i):
        return OccupancyFrame(np.full((3, 3), float(i)), np.zeros(3, np.uint8), i, float(self.stamps[i]), {"k": i})


def test_a_range_is_a_scene_from_its_first_frame_with_the_truth_sliced():
    part = FrameRange(_Scene(10), 4, 7)
    assert len(part) == 4 and part.name == "made-up[4-7]" and part.predictor == "the source's own"
    frame = part[0]
    assert frame.index == 0 and frame.points[0, 0] == 4.0 and frame.stamp == 102.0
    assert frame.meta == {"k": 4, "source_index": 4}
    np.testing.assert_array_equal(part.gt_poses, _Scene(10).gt_poses[4:8])
    np.testing.assert_array_equal(part.stamps, [102.0, 102.5, 103.0, 103.5])
    with pytest.raises(IndexError):
        part[4]
    with pytest.raises(ConfigError):
        FrameRange(_Scene(10), 8, 10)


def test_occvo_run_takes_keyframes_of_a_drive_only(capsys):
    from occvo_cli.cli import main

    assert main(["run", "--synthetic", "--keyframes", "2-4", "--quiet"]) == 2
    assert "nuScenes drive" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["run", "--synthetic", "--keyframes", "4-2", "--quiet"])
    assert exc.value.code == 2 and "0 <= A <= B" in capsys.readouterr().err
