"""A nuScenes drive converted to a ROS 2 recording (occvo convert-drive: one MCAP file, a Humble bag, a Jazzy bag) and
read back by occvo run --input: the same occupancy frames bit for bit, the same poses as the drive's own LiDAR run,
its camera topics equal to the JPEGs and calibration; bad recordings are one line, exit 2."""

import json
from pathlib import Path

import numpy as np
import pytest
from nuscenes_sample import DRIVE, drive_root


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    drive_root()
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.lidar.source import LidarOccupancyScene
    from occvo_core.recording.convert_drive import convert_drive

    class Cached(LidarOccupancyScene):  # each frame made once for the three recordings and the comparisons
        frames: dict = {}

        def __getitem__(self, index):
            if index not in self.frames:
                self.frames[index] = super().__getitem__(index)
            return self.frames[index]

    source = Cached(NuScenesDrive(DRIVE, scene="scene-0916"))
    root = tmp_path_factory.mktemp("recordings")
    paths = {"mcap": root / "drive.mcap", "humble": root / "humble_bag", "jazzy": root / "jazzy_bag"}
    paths["cameras_bag"] = root / "cameras_bag"
    convert_drive(source, paths["mcap"], distro="jazzy")
    convert_drive(source, paths["cameras_bag"], distro="jazzy", storage="sqlite3")  # with the six cameras
    convert_drive(source, paths["humble"], distro="humble", storage="sqlite3", images=False)
    convert_drive(source, paths["jazzy"], distro="jazzy", storage="mcap", images=False)
    return source, paths


@pytest.mark.parametrize("form", ["mcap", "humble", "jazzy"])
def test_the_recording_gives_the_drives_frames_bit_for_bit(converted, form):
    from occvo_core.datasets import open_scene

    source, paths = converted
    recorded = open_scene(paths[form])
    assert len(recorded) == len(source) == 41 and recorded.name == source.name
    for i in range(len(source)):
        a, b = source[i], recorded[i]
        assert a.points.dtype == b.points.dtype == np.float64 and np.array_equal(a.points, b.points)
        assert np.array_equal(a.labels, b.labels) and a.stamp == b.stamp
    assert recorded.config_defaults == source.config_defaults and recorded.gt_on_map_plane
    np.testing.assert_allclose(recorded.gt_poses, source.gt_poses, rtol=0, atol=1e-9)


def test_occvo_run_on_the_mcap_and_the_bag_gives_the_drives_poses(converted, tmp_path, capsys):
    from occvo_cli.cli import build_parser, main
    from occvo_cli.commands.run import config_from_args
    from occvo_core.datasets import open_scene
    from occvo_core.pipeline import OdometryPipeline

    source, paths = converted

    def run(src):  # as occvo run configures a run: the source's own defaults
        config = config_from_args(build_parser().parse_args(["run"]), src)
        return OdometryPipeline(src, config, threads=1, progress=False).run()

    direct = run(source)
    for form in ("mcap", "humble"):
        recorded = run(open_scene(paths[form]))
        assert np.array_equal(recorded.odometry.poses, direct.odometry.poses), form  # bit for bit: within 1e-9 m
        assert recorded.summary()["ape_rmse_m"] == direct.summary()["ape_rmse_m"] <= 0.10
    out = tmp_path / "out"  # the command's own way in: the same source, config and ground truth
    assert main(["run", "--input", str(paths["mcap"]), "--frames", "3", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 3 and summary["ape_on_map_plane"] and summary["scene"] == source.name
    run_json = json.loads((out / "run.json").read_text())
    assert run_json["config"]["voxel_pfilter"]["p_index_threshold"] == 0.9  # the LiDAR source's own defaults
    capsys.readouterr()


def test_occvo_run_from_images_on_the_bag_the_mcap_and_the_drive_gives_the_same_poses(converted, tmp_path, capsys):
    """`occvo run --input bag_dir/ --from-images` (the converter's bag of the drive's six cameras), the same on the MCAP
    file, and on the drive itself (the nuScenes reader): the same poses, one thread each (torch's sums split by
    thread count). In memory as the command builds its run, and the command itself on the bag."""
    from occvo_cli.cli import build_parser, main
    from occvo_cli.commands.run import _first_frames, _image_source, config_from_args
    from occvo_core.pipeline import OdometryPipeline
    from occvo_core.trajectory import read_tum

    source, paths = converted
    frames = 4

    def run(path):
        args = build_parser().parse_args(["run", "--input", str(path), "--from-images", "--threads", "1"])
        images = _first_frames(_image_source(args), frames)
        return OdometryPipeline(images, config_from_args(args, images), threads=1, progress=False).run()

    drive = run(DRIVE)  # scene-0916, the drive's one scene
    assert len(drive.odometry.poses) == frames
    for form in ("cameras_bag", "mcap"):
        recorded = run(paths[form])
        np.testing.assert_allclose(recorded.odometry.poses, drive.odometry.poses, rtol=0, atol=1e-9, err_msg=form)
        assert np.array_equal(recorded.stamps(), drive.stamps()), form
    out = tmp_path / "out"
    argv = ["run", "--input", str(paths["cameras_bag"]), "--from-images", "--threads", "1", "--frames", str(frames)]
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    stamps, poses = read_tum(out / "trajectory.tum")  # written to 1e-9 (%.9f)
    np.testing.assert_allclose(poses[:, :3, 3], drive.odometry.poses[:, :3, 3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(stamps, drive.stamps(), rtol=0, atol=1e-9)
    capsys.readouterr()


def test_the_camera_topics_are_the_jpegs_and_calibration(converted):
    from occvo_core.datasets.ros2_cameras import RecordedCameras

    source, paths = converted
    drive = source.drive
    cams = RecordedCameras(paths["mcap"])
    assert len(cams) == len(drive)
    for i in (0, 20, 40):
        k = drive[i]
        assert cams.jpegs(i) == [Path(f).read_bytes() for f in k.files]
        K, size = cams.intrinsics(i)
        assert np.array_equal(K, k.intrinsics) and size == (1600, 900)
        assert np.array_equal(cams.camera_stamps(i), k.camera_stamps)
    np.testing.assert_allclose(cams.cam_to_ego, drive[0].cam_to_ego, rtol=0, atol=1e-12)


def test_the_camera_model_sees_the_recordings_cameras_as_the_drives(converted):
    """--from-images on a recording: the network's input and output as from the drive's own files."""
    from occvo_core.datasets.ros2_cameras import RecordedCameras
    from occvo_core.models.image_source import NuScenesImageSource
    from occvo_core.models.tpvformer.checkpoint import SHIPPED_THRESHOLDS, shipped_checkpoint
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor

    source, paths = converted
    predictor = OccupancyPredictor(shipped_checkpoint(), min_confidence=SHIPPED_THRESHOLDS[0],
                                   min_ground_confidence=SHIPPED_THRESHOLDS[1], camera_mask=True)  # fmt: skip
    drive = NuScenesImageSource(source.drive, predictor)
    recorded = NuScenesImageSource(RecordedCameras(paths["mcap"]), predictor)
    assert recorded.name == drive.name and len(recorded) == len(drive)
    np.testing.assert_array_equal(recorded.stamps, drive.stamps)
    np.testing.assert_allclose(recorded.gt_poses, drive.gt_poses, rtol=0, atol=1e-9)
    images, k, cam_to_ego = recorded.camera_frame(20)
    want = drive.camera_frame(20)
    assert np.array_equal(images, want[0]) and np.array_equal(k, want[1])
    np.testing.assert_allclose(cam_to_ego, want[2], rtol=0, atol=1e-12)  # /tf_static's quaternions
    a, b = recorded[20], drive[20]
    assert a.stamp == b.stamp and len(a.points) == len(b.points) and np.array_equal(a.labels, b.labels)
    assert np.array_equal(a.points, b.points)


def test_bag_versions_and_latched_topics(converted):
    from rosbags.interfaces import QosDurability
    from rosbags.rosbag2 import Reader
    from ruamel.yaml import YAML

    _, paths = converted
    for form, version in (("humble", 5), ("jazzy", 8)):
        meta = YAML(typ="safe").load((paths[form] / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["version"] == version
        with Reader(paths[form]) as reader:
            assert reader.message_count == 1 + 2 * 41
            qos = {c.topic: c.ext.offered_qos_profiles[0].durability for c in reader.connections}
        assert qos["/occvo/source"] == QosDurability.TRANSIENT_LOCAL
        assert qos["/occvo/occupancy"] == QosDurability.VOLATILE


def test_bad_recordings_are_one_line(converted, tmp_path, capsys):
    from occvo_cli.cli import main

    _, paths = converted
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(paths["mcap"].read_bytes()[:5000])
    assert main(["run", "--input", str(broken), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken.mcap" in err[0] and "recording" in err[0], err
    assert main(["run", "--input", str(paths["jazzy"]), "--occupancy-topic", "/points", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no topic /points" in err[0] and "/occvo/occupancy" in err[0], err
    assert main(["convert-drive", "--input", str(tmp_path), "--out", str(tmp_path / "x.mcap")]) == 2
    assert "not a nuScenes drive" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # a usage error: argparse's, before any work
        main(["convert-drive", "--input", str(DRIVE), "--out", str(paths["mcap"])])
    assert exit_.value.code == 2 and "already exists" in capsys.readouterr().err
