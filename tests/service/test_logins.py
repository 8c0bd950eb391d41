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
