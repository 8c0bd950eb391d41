"""occvo on a ROS 2 graph over Zenoh, seen by a ROS 2 participant that is not occvo's code (zenoh-ros2-sdk, which
speaks rmw_zenoh's keys, CDR, attachments and liveliness tokens): on a loopback router, with the service's workers
and `python -m occvo_services.ros2` as processes, it publishes the release scene's occupancy clouds and receives
occvo's nav_msgs/Odometry (the poses OccVO registers offline on the same clouds, to 1e-9 m), finds occvo's node and
topics in a graph query, gets the latched map as a late subscriber, and the six camera topics of the real drive are
turned into poses. The type hashes agree with rosbags' and the SDK's, the keys with pamoja-ros2's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from occvo_services.local import REPO, LocalService
from occvo_services.ros2.names import dds_type_name, topic_key
from occvo_services.ros2.type_hash import rihs01

sdk = pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk (the dev extra) is the ROS 2 participant")

DATA = Path(__file__).resolve().parents[3] / "shared/data"
SCENE = DATA / "occvo-sample/occupancy/scene-0101"
DRIVE = DATA / "nuscenes-mini"
STORE = get_typestore(Stores.ROS2_JAZZY)
BLOCK = zenoh.CongestionControl.BLOCK  # a test's own puts: none dropped on a busy host
DOMAIN, NAMESPACE = 7, "/robot1"
TYPES = [  # every message type occvo's node sends or takes
    "nav_msgs/msg/Odometry",
    "tf2_msgs/msg/TFMessage",
    "nav_msgs/msg/Path",
    "sensor_msgs/msg/PointCloud2",
    "sensor_msgs/msg/CompressedImage",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CameraInfo",
]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))


def _msg_text(name: str) -> str:
    """A .msg file of the type, from rosbags' definitions (the SDK would fetch them from git)."""

    def typ(desc) -> str:
        kind, arg = desc
        if kind.name == "NAME":
            pkg, _, base = arg.split("/")
            return f"{pkg}/{base}"
        if kind.name == "BASE":
            return arg[0] + (f"<={arg[1]}" if arg[1] else "")
        inner, n = arg
        return typ(inner) + (f"[{n}]" if kind.name == "ARRAY" else f"[<={n}]" if n else "[]")

    consts, fields = STORE.fielddefs[name]
    lines = [f"{t} {c} = {v}" for c, t, v in consts] + [f"{typ(d)} {f}" for f, d in fields]
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module", autouse=True)
def sdk_closed():
    """The SDK's one session closed after the module: its threads would keep pytest from exiting."""
    yield
    from zenoh_ros2_sdk import ZenohSession

    if ZenohSession._instance is not None:
        ZenohSession._instance.close()


_MESSAGES: list[Path] = []  # the SDK's registry is one a process: one folder for every module using the fixture


@pytest.fixture(scope="module")
def messages(tmp_path_factory):
    """Local message definitions for the SDK, every type it may need: no git, no network."""
    if _MESSAGES:
        return _MESSAGES[0]
    root = tmp_path_factory.mktemp("msgs")
    for name in STORE.fielddefs:
        pkg, kind, base = name.split("/")
        if kind != "msg":
            continue
        (root / pkg / kind).mkdir(parents=True, exist_ok=True)
        (root / pkg / kind / f"{base}.msg").write_text(_msg_text(name))
    from zenoh_ros2_sdk.message_registry import get_registry

    registry = get_registry(str(root))
    assert registry.messages_dir == root, "the SDK's registry was made before this fixture"
    _MESSAGES.append(root)
    return root


def start_node(service: LocalService, tmp_path: Path, *settings: str) -> tuple[subprocess.Popen, Path]:
    cfg = tmp_path / "ros2.json5"
    cfg.write_text("{" + ", ".join([f"domain_id: {DOMAIN}", f'namespace: "{NAMESPACE}"', *settings]) + "}")
    log = tmp_path / "ros2.log"
    cmd = [sys.executable, "-m", "occvo_services.ros2", "--connect", service.endpoint, "--config", str(cfg)]
    cmd += ["--log-level", "DEBUG"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=ENV, stderr=open(log, "w"))
    return proc, log


def stop_node(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGUSR1)  # its threads' stacks into its log, for a failure's report
        time.sleep(0.5)
    proc.terminate()
    try:
        return proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait(10)


def wait_for(cond, timeout: float, what: str, node: subprocess.Popen | None = None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert node is None or node.poll() is None, f"occvo's ROS 2 node exited with code {node.returncode}"
        value = cond()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def sdk_session(service: LocalService):
    from zenoh_ros2_sdk import ZenohSession, get_registry

    port = int(service.endpoint.rsplit(":", 1)[1])
    old = ZenohSession._instance  # the SDK keeps one session a process: the last test's is on another router
    if old is not None and old.router_port != port:
        old.close()
    if ZenohSession._instance is None:  # a new session (another module's was closed by its sdk_closed)
        get_registry()._loaded_types.clear()  # the types lived in the closed session's store
    return ZenohSession.get_instance("127.0.0.1", port), port


def test_type_hashes_and_keys_agree_with_other_libraries():
    from zenoh_ros2_sdk.utils import get_type_hash

    pamoja = pytest.importorskip("pamoja.ros2", reason="pamoja-ros2 (the dev extra) assembles rmw_zenoh keys")
    for name in TYPES:
        ours = rihs01(STORE, name)
        assert ours == STORE.hash_rihs01(name), name  # rosbags' implementation of REP-2011
        deps = {n: _msg_text(n) for n in STORE.fielddefs if n != name}
        assert ours == get_type_hash(name, msg_definition=_msg_text(name), dependencies=deps), name  # the SDK's own
        assert dds_type_name(name) == pamoja.dds_type_name(name)
        assert topic_key(3, "/robot1/occvo/odom", name, ours) == pamoja.entity_key(3, "/robot1/occvo/odom", name, ours)


def test_the_hash_sees_a_changed_definition():
    """The same type name with a field renamed or retyped gets another hash: an old subscriber no longer matches."""
    from rosbags.typesys import get_types_from_msg

    def hashed(text: str) -> str:
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(text, "occvo_test/msg/A"))
        ours = rihs01(store, "occvo_test/msg/A")
        assert ours == store.hash_rihs01("occvo_test/msg/A")
        return ours

    assert (
        len({hashed("float64 x\nfloat64 y\n"), hashed("float64 x\nfloat64 yy\n"), hashed("float64 x\nfloat32 y\n")})
        == 3
    )


def offline_poses(frames, stamps=None, bag=None) -> np.ndarray:
    """The poses OccVO registers on the frames before loop closure (register's pose, as the service publishes it);
    with `bag`, each pose also written there at its stamp as `occvo run --ros2-bag` writes it."""
    from occvo_core import OccVO, OccVOConfig
    from occvo_core.viz.ros2_bag import Ros2Bag

    vo = OccVO(OccVOConfig())
    vo.reset()
    out, writer = [], None if bag is None else Ros2Bag(bag)
    for i, f in enumerate(frames):
        reg = vo.register(f)
        out.append(reg.pose)
        result = vo.complete(reg)
        if writer is not None:
            writer.pose(stamps[i], result.pose, result.covariance, result.loop_correction)
    if writer is not None:
        writer.close()
    return np.array(out)


def bag_odometry(bag: Path) -> list:
    from rosbags.rosbag2 import Reader

    from occvo_core.viz.ros2_bag import STORE as BAG_STORE

    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == "/occvo/odom"]
        return [BAG_STORE.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]


def cloud_kwargs(pc2, field_cls, frame, ns: int) -> dict:
    """A frame as PointCloud2 fields: x, y, z float32 and class uint8, 13 bytes a point, little-endian."""
    rec = np.zeros(len(frame.points), np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("class", "u1")]))
    for i, a in enumerate("xyz"):
        rec[a] = frame.points[:, i]
    rec["class"] = frame.labels
    fields = [
        field_cls(name=n, offset=o, datatype=t, count=1)
        for n, o, t in [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("class", 12, 2)]
    ]
    return dict(
        header=header(ns, "base_link"),
        height=1,
        width=len(rec),
        fields=fields,
        is_bigendian=False,
        point_step=13,
        row_step=13 * len(rec),
        data=np.frombuffer(rec.tobytes(), np.uint8),
        is_dense=True,
    )


def header(ns: int, frame_id: str):
    from zenoh_ros2_sdk import get_message_class

    time_cls, header_cls = get_message_class("builtin_interfaces/msg/Time"), get_message_class("std_msgs/msg/Header")
    return header_cls(stamp=time_cls(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame_id)


def pose_of(odom) -> np.ndarray:
    p, q = odom.pose.pose.position, odom.pose.pose.orientation
    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    M[:3, 3] = [p.x, p.y, p.z]
    return M


@pytest.fixture(scope="module")
def service():
    s = LocalService(quiet=True)
    s.start()
    yield s
    s.stop()


@pytest.mark.skipif(not SCENE.is_dir(), reason=f"the OCC-VO release sample is not at {SCENE}")
def test_occupancy_clouds_in_odometry_out(messages, service, tmp_path):
    from zenoh_ros2_sdk import (
        ROS2Publisher,
        ROS2Subscriber,
        get_message_class,
        get_topic_info,
        get_topic_names_and_types,
    )

    from occvo_core.datasets.occvo_release import OccVOReleaseScene

    scene = OccVOReleaseScene(SCENE)
    frames = [scene[i] for i in range(10)]
    for f in frames:  # the frames as the clouds carry them: float32 coordinates
        f.points = f.points.astype(np.float32).astype(np.float64)
    stamps = [1_533_151_603_547_590_000 + 500_000_000 * i for i in range(len(frames))]
    want = offline_poses(frames, stamps, tmp_path / "offline_bag")
    # the map renamed to one level: the SDK finds a latched topic's publishers by its name with only the leading
    # '/' mangled ('%occvo/map'), where rmw_zenoh mangles every '/' ('%occvo%map')
    node, log = start_node(service, tmp_path, 'topics: {map: "/occvo_map"}')
    session, port = sdk_session(service)
    got, service_poses = [], []
    try:
        ROS2Subscriber(
            "/occvo/odom", "nav_msgs/msg/Odometry", got.append, domain_id=DOMAIN, router_port=port, node_name="checker"
        )
        session.session.declare_subscriber(
            "occvo/*/pose", lambda s: service_poses.append((str(s.key_expr), s.payload.to_bytes()))
        )
        pub = ROS2Publisher(
            "/occvo/occupancy", "sensor_msgs/msg/PointCloud2", domain_id=DOMAIN, router_port=port, node_name="drive"
        )
        blocking(pub, session)  # every cloud reaches the node, as the poses are counted
        # the graph as `ros2 topic info -v` sees it: occvo's subscription is up before the first cloud goes out
        info = wait_for(
            lambda: (
                (i := get_topic_info("/occvo/occupancy", domain_id=DOMAIN, router_port=port, verbose=True))
                and i.subscriber_count
                and i
            ),
            60,
            "occvo's node",
            node,
        )
        assert [(s.node_name, s.node_namespace) for s in info.subscribers] == [("occvo", NAMESPACE)]
        topics = dict(get_topic_names_and_types(domain_id=DOMAIN, router_port=port))
        for topic, typ in [
            ("/occvo/odom", "nav_msgs/msg/Odometry"),
            ("/tf", "tf2_msgs/msg/TFMessage"),
            ("/occvo/path", "nav_msgs/msg/Path"),
            ("/occvo_map", "sensor_msgs/msg/PointCloud2"),
            ("/occvo/occupancy", "sensor_msgs/msg/PointCloud2"),
        ]:
            assert topics.get(topic) == [typ], (topic, topics)
        nodes = {
            str(r.ok.key_expr) for r in session.liveliness.get(f"@ros2_lv/{DOMAIN}/*/*/*/NN/**", timeout=2) if r.ok
        }
        assert any(k.endswith("/NN/%/%robot1/occvo") for k in nodes), nodes

        # as a ROS 2 publisher waits for its subscription to match: a sample put before its route exists is dropped
        wait_for(lambda: pub.pub.matching_status.matching, 30, "occvo's subscription to match", node)
        field_cls = get_message_class("sensor_msgs/msg/PointField")
        for f, ns in zip(frames, stamps):
            pub.publish(**cloud_kwargs(None, field_cls, f, ns))
        wait_for(lambda: len(got) >= len(frames), 300, f"{len(frames)} odometry messages ({len(got)} came)")
        est = np.array([pose_of(m) for m in got])
        assert np.abs(est[:, :3, 3] - want[:, :3, 3]).max() <= 1e-9
        assert np.abs(est[:, :3, :3] - want[:, :3, :3]).max() <= 1e-9
        assert {(m.header.frame_id, m.child_frame_id) for m in got} == {("odom", "base_link")}
        assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got] == stamps
        # the covariances the offline bag holds for the same frames (fine GICP's information, the twist's from
        # consecutive poses): zero for the first pose, which defines odom, and never "certainly standing still"
        offline = bag_odometry(tmp_path / "offline_bag")
        for m, o in zip(got[: len(frames)], offline, strict=True):
            np.testing.assert_allclose(np.asarray(m.pose.covariance), o.pose.covariance, rtol=1e-9, atol=1e-300)
            np.testing.assert_allclose(np.asarray(m.twist.covariance), o.twist.covariance, rtol=1e-9, atol=1e-300)
        assert not np.any(got[0].pose.covariance) and min(np.asarray(got[0].twist.covariance)[[0, 7, 14]]) >= 1e6
        assert all(min(np.asarray(m.pose.covariance)[[0, 7, 14]]) > 0 for m in got[1:])
        assert all(max(np.asarray(m.pose.covariance)[[0, 7, 14]]) < 1 for m in got[1:])  # measured, not unknown
        speed = np.array([m.twist.twist.linear.x for m in got[1:]])
        step = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1) / 0.5
        assert np.allclose(np.abs(speed), step, rtol=0.05, atol=0.05)

        # a late subscriber of the latched map gets the last map the node published
        maps = []
        ROS2Subscriber(
            "/occvo_map",
            "sensor_msgs/msg/PointCloud2",
            maps.append,
            domain_id=DOMAIN,
            router_port=port,
            node_name="late",
            qos=":1:,1:,:,:,,",  # transient local, depth 1
        )
        wait_for(lambda: maps, 30, "the latched map")
        assert maps[0].header.frame_id == "odom" and maps[0].width > 1000

        # a malformed message: one line in the node's log, and the node goes on (put with BLOCK, as the clouds:
        # dropped on a busy host, the log had no line to count)
        session.session.put(pub.keyexpr, b"\x00\x01\x00\x00\xff", congestion_control=BLOCK)
        pub.publish(**cloud_kwargs(None, field_cls, frames[0], stamps[-1] + 500_000_000))
        wait_for(lambda: len(got) > len(frames), 60, "a pose after the malformed message")
        assert node.poll() is None

        # a frame the client sent again is answered again (a full queue, a slow answer): its odometry goes out once
        published = len(got)
        session.session.put(*service_poses[-1], congestion_control=BLOCK)
        time.sleep(2)
        assert len(got) == published
    finally:
        code = stop_node(node)
        text = log.read_text()
    assert code == 0, text
    assert text.count("bad ros message") == 1, text


class CameraRig:
    """A car's six cameras on a ROS 2 graph, as nuscenes2mcap names them (/tf_static, each camera's camera_info and
    image_rect_compressed), and a subscriber of occvo's odometry (`got`); ready when occvo's node has subscribed."""

    def __init__(self, session, port: int, node: subprocess.Popen | None = None):
        from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_message_class

        from occvo_core.cameras import CAMERA_NAMES

        self.cls = {n: get_message_class(n) for n in [
            "geometry_msgs/msg/TransformStamped", "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3",
            "geometry_msgs/msg/Quaternion", "sensor_msgs/msg/RegionOfInterest"]}  # fmt: skip
        kw = dict(domain_id=DOMAIN, router_port=port)
        self.got = []
        ROS2Subscriber("/occvo/odom", "nav_msgs/msg/Odometry", self.got.append, node_name="cam_checker", **kw)
        self.tf = ROS2Publisher("/tf_static", "tf2_msgs/msg/TFMessage", node_name="rig", qos=":1:,1:,:,:,,", **kw)
        self.info = {c: ROS2Publisher(f"/{c}/camera_info", "sensor_msgs/msg/CameraInfo", node_name=f"i{c}", **kw)
                     for c in CAMERA_NAMES}  # fmt: skip
        self.img = {c: ROS2Publisher(f"/{c}/image_rect_compressed", "sensor_msgs/msg/CompressedImage",
                                     node_name=f"c{c}", **kw) for c in CAMERA_NAMES}  # fmt: skip
        for p in [*self.info.values(), *self.img.values()]:
            blocking(p, session)
        for p in [self.tf, *self.info.values(), *self.img.values()]:
            wait_for(lambda p=p: p.pub.matching_status.matching, 60, f"occvo's subscription of {p.topic}", node)

    def send_tf_static(self, frame) -> None:
        self.tf.publish(transforms=camera_messages(frame, self.cls)[0])

    def send(self, frame) -> None:
        """One instant: each camera's calibration, then its image."""
        _, infos, images = camera_messages(frame, self.cls)
        for c, pub in self.info.items():
            pub.publish(**infos[c])
        time.sleep(0.2)  # the calibration before the images (separate topics, no order between them)
        for c, pub in self.img.items():
            pub.publish(**images[c])


def blocking(pub, session) -> None:
    """The SDK publisher's samples put with congestion control BLOCK, as rmw_zenoh puts a keep-all publisher's: the
    SDK maps reliable QoS to BLOCK only where zenoh has a `zenoh.qos` module (zenoh-python 1.x has none), so its puts
    DROP, and on a busy host camera images and clouds were dropped on their way to the node, each such frame lost (one
    pose of two came, or none; three of four clouds). A keep-last driver's messages may be lost so too: the node drops
    that frame, logs `ros messages lost` and goes on
    (test_a_lost_camera_image_costs_one_frame_and_never_mixes_two_instants, tests/service/test_ros2_input_loss.py);
    these tests count every frame's pose."""
    pub.pub.undeclare()
    pub.pub = session.session.declare_publisher(pub.keyexpr, congestion_control=BLOCK)


def camera_messages(frame, cls) -> tuple[list, dict, dict]:
    """A nuScenes keyframe as ROS messages: /tf_static transforms, and per camera its CameraInfo and its JPEG."""
    transforms, infos, images = [], {}, {}
    for im in frame.images:
        ns = round(im.stamp * 1e6) * 1000  # nuScenes counts microseconds
        E = np.asarray(im.extrinsics)
        x, y, z, w = Rotation.from_matrix(E[:3, :3]).as_quat()
        transforms.append(
            cls["geometry_msgs/msg/TransformStamped"](
                header=header(0, "base_link"),
                child_frame_id=im.camera,
                transform=cls["geometry_msgs/msg/Transform"](
                    translation=cls["geometry_msgs/msg/Vector3"](x=E[0, 3], y=E[1, 3], z=E[2, 3]),
                    rotation=cls["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
                ),
            )
        )
        roi = cls["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        infos[im.camera] = dict(
            header=header(ns, im.camera), height=im.height, width=im.width, distortion_model="plumb_bob",
            d=np.zeros(5), k=np.asarray(im.intrinsics, np.float64).ravel(), r=np.eye(3).ravel(),
            p=np.hstack([np.asarray(im.intrinsics), np.zeros((3, 1))]).ravel(), binning_x=0, binning_y=0, roi=roi,
        )  # fmt: skip
        images[im.camera] = dict(header=header(ns, im.camera), format="jpeg", data=np.frombuffer(im.data, np.uint8))
    return transforms, infos, images


@pytest.mark.skipif(not (DRIVE / "v1.0-mini").is_dir(), reason=f"the nuScenes drive is not at {DRIVE}")
def test_six_camera_topics_in_odometry_out(messages, tmp_path):
    """The real drive's six JPEG topics with CameraInfo and /tf_static (nuscenes2mcap's names) become frames of the
    model source (the shipped tiny checkpoint), and each frame a pose on /occvo/odom, stamped with CAM_FRONT's."""

    from occvo_services.nuscenes_source import NuScenesCameraFrames

    ckpt = REPO / "occvo_core/models/tpvformer/weights/tiny.pt"
    service = LocalService(quiet=True, worker_args={"inference": ["--source", "model", "--checkpoint", str(ckpt)]})
    service.start()
    node, log = start_node(service, tmp_path, 'input: "cameras"')
    try:
        session, port = sdk_session(service)
        rig = CameraRig(session, port, node)
        drive = NuScenesCameraFrames(DRIVE)
        frames = [drive[i] for i in range(2)]
        rig.send_tf_static(frames[0])
        for frame in frames:
            rig.send(frame)
        got = rig.got
        wait_for(lambda: len(got) >= len(frames), 600, f"{len(frames)} odometry messages ({len(got)} came)", node)
        want = [round(f.images[0].stamp * 1e6) * 1000 for f in frames]
        assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got] == want
        assert np.allclose(pose_of(got[0]), np.eye(4))  # the first frame defines odom
        assert all(np.isfinite(pose_of(m)).all() for m in got)
    finally:
        code = stop_node(node)
        service.stop()
    assert code == 0, log.read_text()


def test_serve_ros2_supervises_the_node_and_checks_its_settings(tmp_path, monkeypatch):
    """`occvo serve --ros2 --ros2-config FILE` adds the node to what it supervises, run as `python -m
    occvo_services.ros2 --config FILE --connect <router>`; a bad settings file is one line before anything starts."""
    import argparse

    from occvo_core.errors import ConfigError
    from occvo_services import defaults
    from occvo_services.commands import serve
    from occvo_services.supervisor import Supervisor

    def up(*argv):
        parser = argparse.ArgumentParser()
        serve.add_parser(parser.add_subparsers())
        return serve._up_config(parser.parse_args(["serve", *argv]), str(defaults.path("router.json5")))

    good = tmp_path / "robot.json5"
    good.write_text('{domain_id: 3, namespace: "/robot1", topics: {odom: "odometry"}}')
    assert [w.role for w in up().workers] == ["inference", "registration", "map"]
    assert [w.role for w in up("--ros2").workers][-1] == "ros2"
    sup = Supervisor(up("--ros2-config", str(good)), role_names=True)
    cmd = next(c.cmd for c in sup.workers if c.role == "ros2")
    assert cmd[1:3] == ["-m", "occvo_services.ros2"] and cmd[cmd.index("--config") + 1] == str(good)
    assert cmd[cmd.index("--connect") + 1] == sup.endpoint
    bad = tmp_path / "bad.json5"
    bad.write_text("{domain_id: 300}")
    with pytest.raises(ConfigError, match="domain_id"):
        up("--ros2-config", str(bad))
    # on the logins' router (the default) the node runs as login ros2, a client of the service (no worker flags);
    # the router's rules of its domain are test_ros2_logins.py's
    from occvo_services import logins
    from occvo_services.commands._common import secure_default

    monkeypatch.setenv(logins.LOGINS_DIR_ENV, str(tmp_path / "logins"))
    config = up("--ros2-config", str(good))
    assert secure_default(argparse.Namespace(anonymous=False, quiet=True), config, given_router=False)
    node = next(w for w in config.workers if w.role == "ros2")
    assert node.env["OCCVO_ZENOH_CONFIG"] == str(logins.session_file("ros2", tmp_path / "logins").resolve())
    assert "--client-identity" not in node.args
    assert secure_default(argparse.Namespace(anonymous=True, quiet=True), up("--ros2"), given_router=False) is None


def test_attachment_and_bad_clouds():
    """The attachment reads back with the SDK's parser (sequence number, source timestamp, 16-byte gid); a cloud
    without the class field, or with classes in a float field, is refused with the reason."""
    from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment

    from occvo_core.viz import ros_messages as rm
    from occvo_services.ros2.attachment import Attachment
    from occvo_services.ros2.inputs import cloud_frame
    from occvo_services.ros2.names import gid

    g = gid("@ros2_lv/0/zid/0/1/MP/%/%/occvo/%occvo%odom/nav_msgs::msg::dds_::Odometry_/RIHS01_x/::,10:,:,:,,")
    data = Attachment(7, 1_700_000_000_123_456_789, g).encode()
    theirs = SdkAttachment.from_bytes(data)
    assert (len(data), theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (33, 7, 1_700_000_000_123_456_789, g)
    assert Attachment.decode(data) == Attachment(7, 1_700_000_000_123_456_789, g)

    points, labels = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 0.2]]), np.array([4, 11], np.uint8)
    msg = rm.point_cloud(123, "base_link", points, labels)
    frame = cloud_frame(msg)
    assert np.array_equal(frame.points, points.astype(np.float32)) and np.array_equal(frame.labels, labels)
    with pytest.raises(ValueError, match="without field"):
        cloud_frame(msg, class_field="label")
    with pytest.raises(ValueError, match="integer"):
        cloud_frame(msg, class_field="rgb")  # rgb is a float32 field


def test_a_lost_camera_image_costs_one_frame_and_never_mixes_two_instants():
    """Images lost on the way (a keep-last publisher drops samples when the node falls behind): the incomplete set
    is refused naming the cameras it lacks, and the next instant's six images make a frame of their own."""
    import io
    from types import SimpleNamespace

    from PIL import Image

    from occvo_core.viz import ros_messages as rm
    from occvo_services.ros2.inputs import CameraSet

    T = rm.T
    cams = ["A", "B", "C", "D", "E", "F"]
    buf = io.BytesIO()
    Image.new("RGB", (8, 4)).save(buf, "JPEG")
    jpeg = np.frombuffer(buf.getvalue(), np.uint8)

    def image(cam: str, ns: int):
        return T["sensor_msgs/msg/CompressedImage"](header=rm.header(ns, cam), format="jpeg", data=jpeg)

    rig = CameraSet(cams, "base_link")
    ident = T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
        rotation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
    )
    stamped = [T["geometry_msgs/msg/TransformStamped"](rm.header(0, "base_link"), c, ident) for c in cams]
    rig.on_tf_static(T["tf2_msgs/msg/TFMessage"](transforms=stamped))
    for c in cams:
        rig.on_info(c, SimpleNamespace(k=np.array([2.0, 0, 4, 0, 2.0, 2, 0, 0, 1])))  # K is what it reads
    t0, t1, t2 = 10**9, 2 * 10**9, 3 * 10**9
    for c in cams[:5]:  # F's image of t0 lost
        assert rig.on_image(c, image(c, t0)) is None
    with pytest.raises(ValueError, match="no image of F before A's next"):
        rig.on_image("A", image("A", t1))
    for c in cams[1:5]:
        assert rig.on_image(c, image(c, t1)) is None
    frame = rig.on_image("F", image("F", t1))
    assert [im.stamp for im in frame.images] == [2.0] * 6 and rig.stamp_ns == t1  # t1's alone
    for c in cams[::-1][:5]:  # a new set, in another order
        assert rig.on_image(c, image(c, t2)) is None
    assert [im.stamp for im in rig.on_image("A", image("A", t2)).images] == [3.0] * 6
