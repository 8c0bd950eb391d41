"""The login files of `occvo serve`'s default (services/logins.py) and the router config written from them
(services/acl.py): owner-only files, one clear line for bad input, the client rules once per client login with its
prefix, and the worker rules the same as the shipped deploy/acl/router.json5's."""

from __future__ import annotations

import stat
from pathlib import Path

import json5
import pytest

from occvo_core.errors import ConfigError
from occvo_services import acl, defaults, logins
from occvo_services.sessions import client_login

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_first_start_makes_worker_logins_and_one_for_the_user(tmp_path):
    folder = tmp_path / "logins"
    users = logins.ensure(folder)
    assert set(users) == {"inference", "registration", "map", logins.default_login()}
    assert len(set(users.values())) == 4 and all(len(p) >= 24 for p in users.values())
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    for f in folder.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o600, f
    cfg = json5.loads(logins.session_file("registration", folder).read_text())
    assert cfg["transport"]["auth"]["usrpwd"] == {"user": "registration", "password": users["registration"]}
    assert logins.ensure(folder) == users  # a second start keeps them
    (folder / logins.USERS_FILE).write_text("")  # the dictionary emptied by hand: the workers keep their passwords
    again = logins.ensure(folder)
    assert all(again[w] == users[w] for w in logins.WORKER_LOGINS)


def test_add_remove_and_bad_names(tmp_path):
    logins.ensure(tmp_path)
    text = logins.add("robot-1", tmp_path, write=False)
    assert "robot-1" in text and not logins.session_file("robot-1", tmp_path).exists()
    assert logins.login_of(logins.session_file(logins.default_login(), tmp_path)) == logins.default_login()
    assert "robot-1" in logins.client_logins(tmp_path)
    for bad, why in (("a.b", "letters, digits"), ("", "letters, digits"), ("map", "worker"), ("robot-1", "exists")):
        with pytest.raises(ConfigError, match=why):
            logins.add(bad, tmp_path)
    with pytest.raises(ConfigError, match="worker"):
        logins.remove("registration", tmp_path)
    logins.remove("robot-1", tmp_path)
    with pytest.raises(ConfigError, match="no login"):
        logins.remove("robot-1", tmp_path)


def test_only_occvos_own_login_files_prefix_stream_ids():
    """The files occvo writes name their login in `metadata.occvo_login`; deploy/acl's hand-written ones do not (its
    viewer reads every stream, its cameras give their prefix themselves)."""
    assert logins.login_of(DEPLOY / "acl/session-viewer.json5") is None
    assert logins.login_of(DEPLOY / "acl/session-camera.json5") is None
    path = DEPLOY.parent / "no-such-file.json5"
    assert logins.login_of(path) is None


def test_stream_ids_get_the_logins_prefix_once():
    assert logins.own_stream("car0", "alice") == "alice.car0"
    assert logins.own_stream("alice.car0", "alice") == "alice.car0"
    assert logins.own_stream("bob.car0", "alice") == "alice.bob.car0"
    assert logins.own_stream("car0", None) == "car0"


def test_a_client_picks_up_the_users_login_unless_told(tmp_path, monkeypatch):
    monkeypatch.setenv(logins.LOGINS_DIR_ENV, str(tmp_path))
    monkeypatch.delenv("OCCVO_ZENOH_CONFIG", raising=False)
    assert client_login() == (None, False)  # no serve has run here
    logins.ensure(tmp_path)
    own = str(logins.session_file(logins.default_login(), tmp_path))
    assert client_login() == (own, True)
    assert client_login(pick_up=False) == (None, False)  # workers never log in as the user
    monkeypatch.setenv("OCCVO_ZENOH_CONFIG", "/elsewhere.json5")
    assert client_login() == ("/elsewhere.json5", False)


def test_router_config_has_each_client_logins_rules_with_its_prefix(tmp_path):
    logins.ensure(tmp_path)
    logins.add("robot1", tmp_path)
    path = acl.write_router_config(tmp_path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    cfg = json5.loads(path.read_text())
    assert cfg["transport"]["auth"]["usrpwd"]["dictionary_file"] == str((tmp_path / logins.USERS_FILE).resolve())
    assert cfg["listen"]["endpoints"] == ["tcp/127.0.0.1:7447"]
    ac = cfg["access_control"]
    assert ac["enabled"] and ac["default_permission"] == "deny"
    rules = {r["id"]: r for r in ac["rules"]}
    assert rules["robot1_frames"]["key_exprs"] == ["occvo/robot1.$*/camera"]
    assert all(k.startswith("occvo/robot1.$*/") for k in rules["robot1_follow"]["key_exprs"])
    [policy] = [p for p in ac["policies"] if p["subjects"] == ["client_robot1"]]
    assert "robot1_frames" in policy["rules"] and "inference_in" not in policy["rules"]
    for p in (p for p in ac["policies"] if p["subjects"][0].startswith("client_")):
        assert not any(r.startswith(("inference", "registration", "map", "worker")) for r in p["rules"])


def test_worker_rules_are_the_shipped_acls():
    """services/defaults/acl_router.json5 copies deploy/acl/router.json5's worker rules: a change to one is made to
    both."""
    shipped = {r["id"]: r for r in json5.loads((DEPLOY / "acl/router.json5").read_text())["access_control"]["rules"]}
    ours = {r["id"]: r for r in json5.loads(defaults.path("acl_router.json5").read_text())["rules"]}
    assert ours == {k: shipped[k] for k in ours}


def test_robot_logins_are_marked_and_the_nodes_login_is_reserved(tmp_path):
    logins.ensure(tmp_path)
    assert "ros2" not in logins.read_users(tmp_path)  # made only where a node runs
    logins.add("robot1", tmp_path, ros2=True)
    logins.add("alice", tmp_path)
    assert logins.ros2_logins(tmp_path) == ["robot1"]
    assert stat.S_IMODE((tmp_path / logins.ROS2_FILE).stat().st_mode) == 0o600
    with pytest.raises(ConfigError, match="worker"):
        logins.add("ros2", tmp_path)
    users = logins.ensure(tmp_path, node=True)
    assert "ros2" in users and "ros2" not in logins.client_logins(tmp_path)
    logins.remove("robot1", tmp_path)
    assert logins.ros2_logins(tmp_path) == []
    logins.add("robot1", tmp_path)  # the name again, without --ros2: no ROS 2 rights left over
    assert logins.ros2_logins(tmp_path) == []


def test_router_config_with_a_ros2_node_gives_its_keys_to_the_node_and_the_robots_only(tmp_path):
    from occvo_services.ros2.config import Ros2NodeConfig

    logins.ensure(tmp_path)
    logins.add("robot1", tmp_path, ros2=True)
    logins.add("alice", tmp_path)
    node = Ros2NodeConfig.load(None, domain_id=3, namespace="/car")
    node.topics.odom = "odometry"  # relative: under the namespace
    ac = json5.loads(acl.write_router_config(tmp_path, [node]).read_text())["access_control"]
    rules = {r["id"]: r for r in ac["rules"]}
    by_subject = {s: set(p["rules"]) for p in ac["policies"] for s in p["subjects"]}
    assert {s["id"]: s["usernames"] for s in ac["subjects"] if s["id"].startswith("ros2")} == {
        "ros2_node": ["ros2"],
        "ros2_robots": ["robot1"],
    }
    ros2_rules = {r for r in rules if r.startswith("ros2_")}
    assert by_subject["ros2_node"] >= {"ros2_0_in_subscribe_ingress", "ros2_0_out_publish_ingress"}
    assert by_subject["ros2_robots"] >= {"ros2_0_in_publish_ingress", "ros2_0_out_subscribe_ingress"}
    assert not by_subject["ros2_robots"] & {"ros2_0_out_publish_ingress", "ros2_0_in_subscribe_ingress"}
    assert not by_subject["client_alice"] & ros2_rules and not by_subject["client_robot1"] & ros2_rules
    assert "ros2_frames" in by_subject["client_ros2"]  # the node feeds the service on streams ros2.<name>
    assert rules["ros2_frames"]["key_exprs"] == ["occvo/ros2.$*/camera"]
    assert rules["ros2_0_in_publish_ingress"]["key_exprs"] == ["3/occvo/occupancy/*/*", "3/occvo/occupancy/*/*/@adv/**"]
    outs = rules["ros2_0_out_publish_ingress"]["key_exprs"]
    assert "3/car/odometry/*/*" in outs and "3/occvo/map/*/*/@adv/**" in outs
    assert rules["ros2_0_graph_ingress"]["key_exprs"] == ["@ros2_lv/3/**"]
    assert "put" in rules["ros2_0_in_publish_ingress"]["messages"]
    assert "put" not in rules["ros2_0_out_subscribe_ingress"]["messages"]  # a robot never puts on occvo's outputs
    cams = Ros2NodeConfig.load(None, input="cameras").inputs()
    assert len(cams) == 13 and cams[0] == "/tf_static" and "/CAM_BACK/image_rect_compressed" in cams
    # no node: no ROS 2 rule, and no `ros2` login's client rules
    plain = json5.loads(acl.write_router_config(tmp_path).read_text())["access_control"]
    assert not [r for r in plain["rules"] if r["id"].startswith("ros2")]


def test_the_ros2_file_changed_alone_restarts_the_router(tmp_path):
    logins.ensure(tmp_path)
    logins.add("robot1", tmp_path)
    watch = acl.LoginsWatch(tmp_path, every_s=0.0)
    assert not watch()
    (tmp_path / logins.ROS2_FILE).write_text("robot1\n")  # by hand: robot1 given ROS 2 rights
    assert watch() and not watch()
