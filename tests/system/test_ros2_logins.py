"""`occvo serve --ros2` on its default router, with logins and access control: the ROS 2 node runs as login `ros2`,
a robot's login (`occvo logins add robot1 --ros2`, added while serve runs) carries the robot's rmw_zenoh session
config as docs/ros2.md writes it, and the ROS 2 participant that is not occvo's code (zenoh-ros2-sdk) publishes the
release scene's clouds with it and receives occvo's nav_msgs/Odometry, equal to the poses OccVO registers offline.
A session without credentials is refused; a client login without `--ros2` neither sees the graph, nor feeds the
node, nor receives its odometry; the robot's login reads none of the node's occvo streams and cannot publish on the
node's output topics. Real processes, real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import json5
import numpy as np
import pytest
import zenoh
from test_ros2_zenoh import (  # noqa: F401 - messages, sdk_closed: fixtures
    DOMAIN,
    DRIVE,
    NAMESPACE,
    SCENE,
    CameraRig,
    blocking,
    cloud_kwargs,
    messages,
    offline_poses,
    pose_of,
    sdk_closed,
    sdk_session,
    wait_for,
)
from test_serve_logins import REPO, _occvo, _serve, _stop

from occvo_core.viz import ros_messages as rm
from occvo_services import logins
from occvo_services.ros2.names import topic_key
from occvo_services.ros2.type_hash import rihs01
from occvo_services.sessions import zenoh_config

pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk (the dev extra) is the ROS 2 participant")
FRAMES = 4
SETTLE_S = 1.5


def robot_session_config(tmp, login_file, endpoint: str):
    """The robot's rmw_zenoh session config as docs/ros2.md writes it: rmw_zenoh's default (the SDK ships it as
    its own default) with the router's endpoint and the login's usrpwd block copied from its occvo config."""
    from zenoh_ros2_sdk.session import _DEFAULT_SESSION_CONFIG_PATH

    config = json5.loads(_DEFAULT_SESSION_CONFIG_PATH.read_text())
    config["connect"]["endpoints"] = [endpoint]
    config.setdefault("transport", {})["auth"] = json5.loads(login_file.read_text())["transport"]["auth"]
    path = tmp / "robot-session.json5"
    logins.write_private(path, json.dumps(config, indent=1))
    return path


def log_tails(tmp, chars: int = 1500) -> str:
    """The last lines of serve's and each process's log (--log-dir tmp)."""
    names = ("serve.err", "router.log", "ros2.log", "inference.log", "registration.log")
    return "\n".join(f"--- {n}:\n{(tmp / n).read_text()[-chars:]}" for n in names if (tmp / n).is_file())


def added(name: str, endpoint: str, folder, *flags) -> object:
    """`occvo logins add NAME [--ros2]` while serve runs; its config once the restarted router takes it."""
    got = _occvo("logins", "add", name, *flags)
    assert got.returncode == 0, got.stderr
    path = logins.session_file(name, folder)
    opened = wait_for(lambda: _opens(endpoint, path), 30, f"the router to take login {name}")
    opened.close()
    return path


def _opens(endpoint: str, path) -> zenoh.Session | None:
    try:
        return zenoh.open(zenoh_config("client", connect=endpoint, base=path))
    except zenoh.ZError:
        return None


@pytest.mark.skipif(not SCENE.is_dir(), reason=f"the OCC-VO release sample is not at {SCENE}")
@pytest.mark.usefixtures("messages")  # the SDK's local message definitions
def test_serve_ros2_with_logins_a_robot_login_drives_and_others_get_nothing(tmp_path, monkeypatch):
    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_message_class, get_topic_info

    from occvo_core.datasets.occvo_release import OccVOReleaseScene

    folder = tmp_path / "logins"
    monkeypatch.setenv(logins.LOGINS_DIR_ENV, str(folder))  # serve's and `occvo logins`' folder, this test's own
    scene = OccVOReleaseScene(SCENE)
    frames = [scene[i] for i in range(FRAMES)]
    for f in frames:  # the frames as the clouds carry them: float32 coordinates
        f.points = f.points.astype(np.float32).astype(np.float64)
    stamps = [1_533_151_603_547_590_000 + 500_000_000 * i for i in range(FRAMES)]
    want = offline_poses(frames)
    settings = tmp_path / "ros2.json5"
    # the map on one level (the SDK finds a latched topic's publishers by its name with only the leading '/'
    # mangled, test_ros2_zenoh.py), and published every 2 poses
    settings.write_text(
        f'{{domain_id: {DOMAIN}, namespace: "{NAMESPACE}", map_every: 2, topics: {{map: "/occvo_map"}}, '
        'log_level: "DEBUG"}'
    )
    proc, ep, err = _serve(tmp_path, "--ros2", "--ros2-config", str(settings))
    opened = []
    try:
        assert "ros2" in logins.read_users(folder) and logins.ros2_logins(folder) == []
        with pytest.raises(zenoh.ZError):  # no credentials: refused
            zenoh.open(zenoh_config("client", connect=ep, base=None))
        robot1 = added("robot1", ep, folder, "--ros2")
        alice = added("alice", ep, folder)
        assert logins.ros2_logins(folder) == ["robot1"]
        listed = _occvo("logins", "list", "--json")
        roles = {r["login"]: r["role"] for r in json.loads(listed.stdout)["logins"]}
        assert roles["robot1"] == "robot" and roles["alice"] == "client" and roles["ros2"] == "worker"

        # the robot's rmw_zenoh participant, on the config docs/ros2.md gives it
        monkeypatch.setenv("ZENOH_SESSION_CONFIG_URI", str(robot_session_config(tmp_path, robot1, ep)))
        session, port = sdk_session(SimpleNamespace(endpoint=ep))
        got = []
        kw = dict(domain_id=DOMAIN, router_port=port)
        ROS2Subscriber("/occvo/odom", "nav_msgs/msg/Odometry", got.append, node_name="checker", **kw)
        pub = ROS2Publisher("/occvo/occupancy", "sensor_msgs/msg/PointCloud2", node_name="drive", **kw)
        blocking(pub, session)  # every cloud reaches the node, as the poses are counted
        info = wait_for(  # the graph through the router's rules: occvo's subscription, by node and namespace
            lambda: (i := get_topic_info("/occvo/occupancy", verbose=True, **kw)) and i.subscriber_count and i,
            120,
            "occvo's node in the robot's graph",
        )
        assert [(s.node_name, s.node_namespace) for s in info.subscribers] == [("occvo", NAMESPACE)]
        wait_for(lambda: pub.pub.matching_status.matching, 30, "occvo's subscription to match")

        # alice (a client login without --ros2) and robot1 as plain sessions: what each may see while frames flow
        seen = {"alice_ros2": [], "alice_occvo": [], "robot_occvo": [], "robot_odom": []}
        alice_s = zenoh.open(zenoh_config("client", connect=ep, base=alice))
        robot_s = zenoh.open(zenoh_config("client", connect=ep, base=robot1))
        opened += [alice_s, robot_s]
        odom_key = f"{DOMAIN}/occvo/odom/*/*"
        alice_s.declare_subscriber(odom_key, lambda s: seen["alice_ros2"].append(s))
        alice_s.declare_subscriber("occvo/**", lambda s: seen["alice_occvo"].append(str(s.key_expr)))
        robot_s.declare_subscriber("occvo/**", lambda s: seen["robot_occvo"].append(str(s.key_expr)))
        robot_s.declare_subscriber(odom_key, lambda s: seen["robot_odom"].append(s.payload.to_bytes()))
        assert [r for r in alice_s.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2) if r.ok] == []
        assert [r for r in robot_s.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2) if r.ok]  # the robot's: yes
        time.sleep(SETTLE_S)

        field_cls = get_message_class("sensor_msgs/msg/PointField")
        for f, ns in zip(frames, stamps):
            pub.publish(**cloud_kwargs(None, field_cls, f, ns))
        wait_for(lambda: len(got) >= FRAMES, 300, f"{FRAMES} odometry messages ({len(got)} came)")
        est = np.array([pose_of(m) for m in got])
        assert np.abs(est[:, :3, 3] - want[:, :3, 3]).max() <= 1e-9
        assert np.abs(est[:, :3, :3] - want[:, :3, :3]).max() <= 1e-9
        assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got] == stamps

        # alice's cloud is not the node's; a robot's put on occvo's output topic reaches no one
        cloud = rm.point_cloud(stamps[-1] + 10**9, "base_link", frames[0].points, frames[0].labels)
        alice_s.put(pub.keyexpr, bytes(rm.STORE.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2")))
        spoof = b"\x00\x01\x00\x00spoofed odometry"  # from another session: a session gets its own puts itself
        spoofer = zenoh.open(zenoh_config("client", connect=ep, base=robot1))
        opened.append(spoofer)
        spoofer.put(
            topic_key(DOMAIN, "/occvo/odom", "nav_msgs/msg/Odometry", rihs01(rm.STORE, "nav_msgs/msg/Odometry")), spoof
        )
        time.sleep(SETTLE_S)
        last = stamps[-1] + 2 * 10**9
        pub.publish(**cloud_kwargs(None, field_cls, frames[0], last))
        wait_for(lambda: len(got) > FRAMES, 60, "the robot's next pose")
        time.sleep(SETTLE_S)
        assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got] == [*stamps, last]
        assert seen["alice_ros2"] == [] and seen["alice_occvo"] == [] and seen["robot_occvo"] == []
        assert len(seen["robot_odom"]) == FRAMES + 1 and spoof not in seen["robot_odom"]

        # the latched map reaches the robot's late subscriber (zenoh-ext's cache and publisher detection, `@adv`)
        maps = []
        ROS2Subscriber(
            "/occvo_map", "sensor_msgs/msg/PointCloud2", maps.append, node_name="late", qos=":1:,1:,:,:,,", **kw
        )
        wait_for(lambda: maps, 30, "the latched map")
        assert maps[0].header.frame_id == "odom" and maps[0].width > 1000
    except AssertionError as exc:  # what the node, the workers and the router said, in the failure's report
        raise AssertionError(f"{exc}\n{log_tails(tmp_path)}") from None
    finally:
        for s in opened:
            s.close()
        _stop(proc, err)
    node_log = (tmp_path / "ros2.log").read_text()
    assert '"stream": "ros2.ros2-occupancy"' in node_log, node_log[-2000:]


def test_occvo_up_runs_its_ros2_worker_as_the_nodes_login(tmp_path, monkeypatch):
    """A `ros2` worker in `occvo up`'s config (deploy/occvo.json5's commented line) on the logins' router: its
    settings checked as the node's (not as a worker config), "ready" without a token of its own, and the robot's
    login finds the node in the graph."""
    import subprocess
    import sys

    from test_serve_logins import _env

    from occvo_services.sessions import free_port

    monkeypatch.setenv(logins.LOGINS_DIR_ENV, str(tmp_path / "logins"))
    ep = f"tcp/127.0.0.1:{free_port()}"
    workers = [{"role": r, "config": f"{r}.json5"} for r in ("inference", "registration", "map")]
    for w in workers:  # the built-in worker configs, beside the file
        name = "map_service.json5" if w["role"] == "map" else f"{w['role']}_worker.json5"
        (tmp_path / w["config"]).write_text((REPO / "services/defaults" / name).read_text())
    (tmp_path / "ros2_node.json5").write_text(f'{{domain_id: {DOMAIN}, namespace: "{NAMESPACE}"}}')
    workers.append({"role": "ros2", "config": "ros2_node.json5"})
    (tmp_path / "up.json5").write_text(json.dumps({"router": {"listen": ep}, "workers": workers}))
    err = open(tmp_path / "up.err", "w")  # noqa: SIM115 - closed with the process
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "up", "--json", "--config", str(tmp_path / "up.json5")],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=err, text=True,
    )  # fmt: skip
    session = None
    try:
        line = {"event": None}
        while line["event"] != "ready":
            text = proc.stdout.readline()
            assert text, (tmp_path / "up.err").read_text()[-2000:]
            line = json.loads(text)
        session = zenoh.open(
            zenoh_config("client", connect=ep, base=added("robot1", ep, tmp_path / "logins", "--ros2"))
        )
        nodes = wait_for(
            lambda: [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{DOMAIN}/*/*/*/NN/**") if r.ok],
            60,
            "occvo's node in the robot's graph",
        )
        assert any(k.endswith("/NN/%/%robot1/occvo") for k in nodes), nodes
    finally:
        if session is not None:
            session.close()
        _stop(proc, err)
    assert "ros2" in logins.read_users(tmp_path / "logins")


@pytest.mark.skipif(not (DRIVE / "v1.0-mini").is_dir(), reason=f"the nuScenes drive is not at {DRIVE}")
@pytest.mark.usefixtures("messages")
def test_a_robot_login_drives_the_camera_input(tmp_path, monkeypatch):
    """The camera input behind the rules: the robot's /tf_static (a transient-local publisher), six CameraInfo and
    six JPEG topics of the real drive's first keyframe make one frame and one pose. (/tf_static is put once the
    node's subscription matched, so it goes as a sample: the latched cache behind the rules is the map's test.)"""

    from occvo_services.nuscenes_source import NuScenesCameraFrames

    folder = tmp_path / "logins"
    monkeypatch.setenv(logins.LOGINS_DIR_ENV, str(folder))
    settings = tmp_path / "cams.json5"
    settings.write_text(f'{{domain_id: {DOMAIN}, input: "cameras"}}')
    ckpt = REPO / "occvo_core/models/tpvformer/weights/tiny.pt"
    proc, ep, err = _serve(tmp_path, "--ros2-config", str(settings), "--source", "model", "--checkpoint", str(ckpt))
    try:
        robot1 = added("robot1", ep, folder, "--ros2")
        monkeypatch.setenv("ZENOH_SESSION_CONFIG_URI", str(robot_session_config(tmp_path, robot1, ep)))
        session, port = sdk_session(SimpleNamespace(endpoint=ep))
        rig = CameraRig(session, port)
        got = rig.got
        frame = NuScenesCameraFrames(DRIVE)[0]
        rig.send_tf_static(frame)
        rig.send(frame)
        wait_for(lambda: got, 300, "the camera frame's odometry")
        assert (
            got[0].header.stamp.sec * 10**9 + got[0].header.stamp.nanosec == round(frame.images[0].stamp * 1e6) * 1000
        )
        assert np.allclose(pose_of(got[0]), np.eye(4))  # the first frame defines odom
    finally:
        _stop(proc, err)
    assert "ros message refused" not in (tmp_path / "ros2.log").read_text()
