"""`occvo run --mcap` and `--ros2-bag` on the real scene-0101 read back with the mcap and rosbags readers: one pose a
frame at the data's stamps equal to trajectory.tum (odom -> base_link, map -> odom), its covariance and twist, the
path, and class-coloured point clouds with the class as a field; the map latched; Humble's and Jazzy's bag versions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from occvo_cli.cli import main

pytest.importorskip("foxglove", reason="foxglove-sdk is in the foxglove extra")
pytest.importorskip("rosbags", reason="rosbags is in the ros extra")
mcap_reader = pytest.importorskip("mcap.reader", reason="mcap is in the foxglove extra")
protobuf = pytest.importorskip("mcap_protobuf.decoder", reason="mcap-protobuf-support is in the dev extra")


@pytest.fixture(scope="module")
def run(tmp_path_factory, sample_root):
    d = tmp_path_factory.mktemp("robotics")
    scene = sample_root / "occupancy" / "scene-0101"
    argv = ["run", "--quiet", "--input", str(scene), "--out", str(d / "out"), "--mcap", str(d / "run.mcap")]
    assert main([*argv, "--ros2-bag", str(d / "bag")]) == 0
    from occvo_core.trajectory import read_tum

    stamps, poses = read_tum(d / "out" / "trajectory.tum")
    return d, stamps, poses, scene


def _mcap(path):
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[protobuf.DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((schema.name, message.log_time, decoded))
    return out


def test_the_mcap_holds_poses_at_the_datas_stamps_the_path_and_point_clouds(run):
    d, stamps, poses, _ = run
    topics = _mcap(d / "run.mcap")
    assert {t: {m[0] for m in ms} for t, ms in topics.items()} == {
        "/tf": {"foxglove.FrameTransform"},
        "/occvo/odom": {"foxglove.PoseInFrame"},
        "/occvo/path": {"foxglove.PosesInFrame"},
        "/occvo/occupancy": {"foxglove.PointCloud"},
        "/occvo/map": {"foxglove.PointCloud"},
    }
    tf = topics["/tf"][1::2]  # map -> odom, then odom -> base_link
    assert len(tf) == 40 == len(stamps)
    for (_, log_time, t), stamp, pose in zip(tf, stamps, poses):
        assert log_time == round(stamp * 1e6) * 1000  # the data's clock counts microseconds
        assert t.timestamp.seconds * 10**9 + t.timestamp.nanos == log_time
        assert (t.parent_frame_id, t.child_frame_id) == ("odom", "base_link")  # no loop closed: odom is map
        np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z], pose[:3, 3], atol=1e-8)
    assert {(t.parent_frame_id, t.child_frame_id) for _, _, t in topics["/tf"][::2]} == {("map", "odom")}
    last_path = topics["/occvo/path"][-1][2]
    assert len(last_path.poses) == 40 and last_path.frame_id == "map"
    np.testing.assert_allclose(
        [[p.position.x, p.position.y, p.position.z] for p in last_path.poses], poses[:, :3, 3], atol=1e-8
    )
    clouds = topics["/occvo/occupancy"]
    assert len(clouds) == 40
    cloud = clouds[0][2]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "red", "green", "blue", "alpha", "class"]
    assert cloud.frame_id == "base_link" and len(cloud.data) % cloud.point_stride == 0 and len(cloud.data) > 0
    assert topics["/occvo/map"][-1][2].frame_id == "map" and len(topics["/occvo/map"][-1][2].data) > len(cloud.data)


def test_the_ros2_bag_holds_odometry_equal_to_the_trajectory_a_path_and_classed_point_clouds(run):
    from rosbags.rosbag2 import Reader

    from occvo_core.datasets import open_scene
    from occvo_core.viz.ros2_bag import STORE

    d, stamps, poses, scene = run
    msgs: dict[str, list] = {}
    with Reader(d / "bag") as reader:
        for connection, t, raw in reader.messages():
            msgs.setdefault(connection.topic, []).append((t, STORE.deserialize_cdr(raw, connection.msgtype)))
        kinds = {c.topic: c.msgtype for c in reader.connections}
    assert kinds == {
        "/occvo/odom": "nav_msgs/msg/Odometry",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/occvo/path": "nav_msgs/msg/Path",
        "/occvo/occupancy": "sensor_msgs/msg/PointCloud2",
        "/occvo/map": "sensor_msgs/msg/PointCloud2",
    }
    odom = msgs["/occvo/odom"]
    assert len(odom) == 40 and len(msgs["/tf"]) == 40
    for (t, o), stamp, pose in zip(odom, stamps, poses):
        assert t == round(stamp * 1e6) * 1000 == o.header.stamp.sec * 10**9 + o.header.stamp.nanosec
        assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_link")
        p, q = o.pose.pose.position, o.pose.pose.orientation
        np.testing.assert_allclose([p.x, p.y, p.z], pose[:3, 3], atol=1e-8)  # trajectory.tum keeps 9 decimals
        np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), pose[:3, :3], atol=1e-8)
    for _, o in odom[1:]:  # a registered frame: a covariance that is one, and the motion since the last
        cov = np.asarray(o.pose.covariance).reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0) and cov[0, 0] < 0.01
        twist = np.asarray(o.twist.covariance).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(twist) > 0)
    speeds = [np.hypot(o.twist.twist.linear.x, o.twist.twist.linear.y) for _, o in odom[1:]]
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) / np.diff(stamps)
    np.testing.assert_allclose(speeds, steps, rtol=0.05, atol=0.05)  # along the car: the path's speed
    for (_, tf), pose in zip(msgs["/tf"], poses):
        (a, b) = tf.transforms
        assert (a.header.frame_id, a.child_frame_id, b.header.frame_id, b.child_frame_id) == (
            "map", "odom", "odom", "base_link"
        )  # fmt: skip
        np.testing.assert_allclose([b.transform.translation.x, b.transform.translation.y], pose[:2, 3], atol=1e-8)
    assert len(msgs["/occvo/path"][-1][1].poses) == 40
    cloud = msgs["/occvo/occupancy"][0][1]
    names = [f.name for f in cloud.fields]
    assert names == ["x", "y", "z", "rgb", "class"]
    field = {f.name: f for f in cloud.fields}
    data = np.asarray(cloud.data).reshape(cloud.width, cloud.point_step)
    classes = data[:, field["class"].offset]
    xyz = data[:, :12].copy().view("<f4")
    frame = open_scene(scene)[0]
    np.testing.assert_array_equal(classes, frame.labels)
    np.testing.assert_allclose(xyz, frame.points.astype(np.float32))
    assert cloud.header.frame_id == "base_link" and msgs["/occvo/map"][-1][1].header.frame_id == "map"


def test_the_map_is_latched_and_the_bag_version_is_the_distributions(run, tmp_path, capsys):
    from rosbags.interfaces import QosDurability
    from rosbags.rosbag2 import Reader
    from ruamel.yaml import YAML

    d = run[0]
    assert main(["run", "--quiet", "--frames", "3", "--out", str(tmp_path / "o"), "--ros2-bag", str(tmp_path / "h"),
                 "--ros-distro", "humble", "--odom-frame", "odom_vo"]) == 0  # fmt: skip
    capsys.readouterr()
    for bag, version in ((d / "bag", 8), (tmp_path / "h", 5)):
        meta = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["version"] == version
        with Reader(bag) as reader:  # rosbags reads both
            qos = {c.topic: c.ext.offered_qos_profiles[0].durability for c in reader.connections}
            odom = next(c for c in reader.connections if c.topic == "/occvo/odom")
            first = _first_message(reader, odom)
        assert qos["/occvo/map"] == QosDurability.TRANSIENT_LOCAL and qos["/occvo/odom"] == QosDurability.VOLATILE
        assert first.header.frame_id == ("odom_vo" if version == 5 else "odom")


def _first_message(reader, connection):
    from occvo_core.viz.ros2_bag import STORE

    _, _, raw = next(reader.messages(connections=[connection]))
    return STORE.deserialize_cdr(raw, connection.msgtype)


def test_a_bag_folder_that_exists_is_refused_before_the_run(tmp_path, capsys):
    (tmp_path / "bag").mkdir()
    assert (
        main(["run", "--quiet", "--frames", "3", "--out", str(tmp_path / "o"), "--ros2-bag", str(tmp_path / "bag")])
        == 2
    )
    assert "already exists" in capsys.readouterr().err


def test_a_unix_stamp_keeps_its_microseconds_and_a_scene_clock_its_nanoseconds():
    from occvo_core.viz.foxglove_log import stamp_ns

    assert stamp_ns(1531883530.449377) == 1531883530_449377000  # nuScenes: microseconds since 1970
    assert stamp_ns(0.5) == 500_000_000 and stamp_ns(12.000000001) == 12_000_000_001
