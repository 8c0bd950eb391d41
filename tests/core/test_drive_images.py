"""The camera chain on the shared real drive: the six JPEGs at the network's input size with matching intrinsics,
the shipped model's frames, and `occvo eval-occ --input DRIVE --labels DIR` scoring them against make-occupancy's
labels inside their camera mask."""

import numpy as np
import pytest
from nuscenes_sample import DRIVE

from occvo_core.grid import FREE


@pytest.fixture(scope="module")
def source(drive):
    from occvo_core.models.image_source import NuScenesImageSource
    from occvo_core.models.tpvformer.checkpoint import shipped_checkpoint
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor

    return NuScenesImageSource(drive, OccupancyPredictor(shipped_checkpoint(), device="cpu"))


@pytest.fixture(scope="module")
def labels(drive, tmp_path_factory):
    from occvo_cli.cli import main

    out = tmp_path_factory.mktemp("labels")
    args = ["make-occupancy", "--input", str(DRIVE), "--keyframes", "3-5", "--sweeps-from", "3-5", "--quiet"]
    assert main([*args, "--out", str(out)]) == 0
    return out


def test_a_keyframes_images_come_at_the_networks_size_with_the_intrinsics_scaled_and_the_real_extrinsics(drive, source):
    images, k, cam_to_ego = source.camera_frame(7)
    width, height = source.predictor.cfg.input_size
    assert images.shape == (6, height, width, 3) and images.dtype == np.uint8
    assert images.reshape(6, -1).std(axis=1).min() > 10  # six real pictures, not a blank
    np.testing.assert_allclose(k, drive.rig(7).scaled(width, height).intrinsics)
    np.testing.assert_array_equal(cam_to_ego, drive[7].cam_to_ego)
    # a LiDAR point seen by CAM_FRONT lands on the same spot of the small image, scaled
    points = drive.lidar_in_ego(7)
    uv, _, seen = drive.rig(7).project(points)
    small, _, _ = drive.rig(7).scaled(width, height).project(points)
    scale = np.array([width / 1600, height / 900])
    np.testing.assert_allclose(small[0][seen[0]], (uv[0][seen[0]] + 0.5) * scale - 0.5, atol=1e-9)


def test_a_frame_is_the_networks_occupancy_stamped_with_the_sample(drive, source):
    frame = source[2]
    assert frame.index == 2 and frame.stamp == drive[2].stamp
    assert len(frame.points) > 0 and np.all(frame.labels < FREE)
    assert frame.meta["token"] == drive[2].token
    np.testing.assert_array_equal(source.gt_poses, drive.gt_poses)


class _Truth:
    """A predictor that answers keyframe i with the labels of keyframe i + shift: scores 1 only when aligned."""

    def __init__(self, drive, labels_root, shift):
        from occvo_core.models.drive_eval import labels_by_token

        self.drive, self.shift = drive, shift
        self.labels, self.index = labels_by_token(labels_root, drive.name)

    def grid(self, i):
        return self.labels.load(self.index[self.drive[i + self.shift].token])[0]


def test_scores_are_one_for_the_labels_themselves_and_lower_for_the_next_keyframes(drive, labels):
    from occvo_core.models.drive_eval import evaluate_drive

    same = evaluate_drive(_Truth(drive, labels, 0), labels, [3, 4]).summary()
    assert same["frames"] == 2 and same["geometry_iou"] == 1.0 and same["miou"] == 1.0
    moved = evaluate_drive(_Truth(drive, labels, 1), labels, [3, 4]).summary()
    assert moved["geometry_iou"] < 0.8


def test_eval_occ_scores_the_shipped_model_on_the_drive_and_says_in_one_line_what_is_missing(labels, capsys):
    import json

    from occvo_cli.cli import main

    args = ["eval-occ", "--input", str(DRIVE), "--labels", str(labels), "--keyframes", "4-5", "--quiet", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 2 and summary["scene"] == "scene-0916" and summary["keyframes"] == [4, 5]
    assert 0.0 <= summary["geometry_iou"] < 1.0 and 0.0 <= summary["miou"] < 1.0
    assert main(["eval-occ", "--input", str(DRIVE), "--labels", str(labels), "--keyframes", "0-1", "--quiet"]) == 2
    assert "no labels for keyframe 0" in capsys.readouterr().err
    assert main(["eval-occ", "--input", str(DRIVE), "--quiet"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
