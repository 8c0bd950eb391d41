"""`occvo serve`'s default is logins and access control, even on loopback: a session without credentials is refused;
the user's own client (the Python client, `occvo replay`, `occvo poses`) logs in by itself and its stream `car0` is
`<login>.car0` on the wire; another login neither publishes on nor reads the first login's streams; a login added by
`occvo logins add` while serve runs works (the router restarts on its own), one removed is refused. `--anonymous`
behaves as before. Real processes, real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services import logins
from occvo_services.client import OccVOClient, camera_frame_of
from occvo_services.commands.replay import replay
from occvo_services.sessions import NoRouterError, free_port, open_session, zenoh_config

REPO = Path(__file__).resolve().parents[2]
SETTLE_S = 1.5


def _env(**extra) -> dict:
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    return {**os.environ, "PYTHONPATH": path, **extra}


def _occvo(*argv, env=None, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "occvo_cli", *argv], cwd=REPO, env=env or _env(), capture_output=True, text=True,
        timeout=timeout, check=False,
    )  # fmt: skip


def _serve(tmp: Path, *flags):
    """`occvo serve` on a free loopback port, until its ready line; returns (process, endpoint)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    err = open(tmp / "serve.err", "w")  # noqa: SIM115 - closed with the process
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "serve", "--listen", ep, "--json", "--log-dir", str(tmp), *flags],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=err, text=True,
    )  # fmt: skip
    line = {"event": None}
    while line["event"] != "ready":
        text = proc.stdout.readline()
        assert text, f"serve ended: {(tmp / 'serve.err').read_text()[-2000:]}"
        line = json.loads(text)
    return proc, ep, err


def _stop(proc, err) -> None:
    proc.send_signal(2)
    try:
        proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    err.close()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serve-logins")
    proc, ep, err = _serve(tmp)
    try:
        yield {"endpoint": ep, "proc": proc, "tmp": tmp, "folder": logins.logins_dir()}
    finally:
        _stop(proc, err)


def _login_session(ep: str, folder: Path, login: str) -> zenoh.Session:
    return zenoh.open(zenoh_config("client", connect=ep, base=logins.session_file(login, folder)))


def test_a_session_without_credentials_is_refused(served):
    ep = served["endpoint"]
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh_config("client", connect=ep, base=None))
    with pytest.raises(NoRouterError, match="refused a session without a login"):
        open_session(ep, pick_up=False)


def test_login_files_are_the_owners_only_and_no_password_in_argv_or_logs(served):
    folder = served["folder"]
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    users = logins.read_users(folder)
    assert {"inference", "registration", "map", logins.default_login()} <= set(users)
    for f in folder.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o600, f
    argv = []
    for pid in subprocess.run(["pgrep", "-f", "occvo"], capture_output=True, text=True).stdout.split():
        try:
            argv.append(Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace"))
        except OSError:
            continue
    logs = (
        "".join(p.read_text(errors="replace") for p in served["tmp"].glob("*.log"))
        + (served["tmp"] / "serve.err").read_text()
    )
    for password in users.values():
        assert password not in "".join(argv) and password not in logs


def test_the_users_client_logs_in_by_itself_and_replays_car0(served, scene, uninterrupted):
    with OccVOClient(served["endpoint"], "car0", timeout=60) as c:
        assert c.login == logins.default_login() and c.stream == f"{c.login}.car0"
        out = replay(c, scene, window=4, timeout=120)
        assert out["poses"] == len(scene) and not c.errors
        for seq, pose in c.poses.items():
            assert (pose.matrix() == uninterrupted[seq]).all()
        assert len(c.trajectory().seqs.to_numpy()) == len(scene)
    got = _occvo("poses", "--stream", "car0", "--connect", served["endpoint"], "--format", "json")
    assert got.returncode == 0, got.stderr
    assert len(got.stdout.splitlines()) == len(scene)
    assert json.loads(got.stdout.splitlines()[0])["stream"] == f"{logins.default_login()}.car0"


def test_occvo_view_follows_the_users_stream_under_its_login(served, scene):
    """The view's subscriptions (poses, occupancy, map updates) are the login's own streams' (the client rules)."""
    rrd = served["tmp"] / "view.rrd"
    view = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "view", "--connect", served["endpoint"], "--stream", "viewed",
         "--rerun", str(rrd), "--seconds", "20"],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        time.sleep(5)  # its subscriptions up
        with OccVOClient(served["endpoint"], "viewed", timeout=60) as c:
            assert replay(c, scene[:4], window=4, timeout=120)["poses"] == 4
        out, err = view.communicate(timeout=60)
    finally:
        if view.poll() is None:
            view.kill()
    counts = json.loads(out.strip().splitlines()[-1])
    assert counts["stream"] == f"{logins.default_login()}.viewed", err
    assert counts["poses"] == 4 and counts["occupancy"] == 4 and counts["map_updates"] >= 1, (counts, err[-2000:])


def _added(served, name: str) -> Path:
    """`occvo logins add NAME`, then the documented step: nothing (serve restarts its router within a second);
    returns the login's config once the router takes it."""
    got = _occvo("logins", "add", name)
    assert got.returncode == 0, got.stderr
    path = logins.session_file(name, served["folder"])
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    deadline = time.monotonic() + 30
    while True:
        try:
            open_session(served["endpoint"], base=path).close()
            return path
        except NoRouterError:
            assert time.monotonic() < deadline, "the added login was not taken within 30 s"
            time.sleep(0.5)


def test_another_login_cannot_publish_on_or_read_the_first_logins_streams(served, scene):
    ep, folder, own = served["endpoint"], served["folder"], logins.default_login()
    _added(served, "mallory")
    victim = f"{own}.victim"
    with OccVOClient(ep, "victim", timeout=60) as c:
        c.wait_for_workers(timeout=30)
        c.reset()
        for f in scene[:3]:
            c.step(f)
        mallory = _login_session(ep, folder, "mallory")
        try:
            got = []
            sub = mallory.declare_subscriber(keys.pose(victim), lambda s: got.append(s))
            errors = mallory.declare_subscriber(keys.errors(victim), lambda s: got.append(s))
            time.sleep(0.5)
            c.step(scene[3])  # a pose of the victim's, published while mallory listens
            for seq in (0, 4):  # a reset of the stream and its next frame, as mallory
                mallory.put(keys.camera(victim), encode(camera_frame_of(scene[seq], victim, seq)))
            time.sleep(SETTLE_S)
            assert got == []  # no pose and no error event of the victim's stream reaches mallory
            for key in (keys.trajectory(victim), keys.pose_latest(victim), keys.map_info(victim)):
                assert [r for r in mallory.get(key, timeout=2.0) if r.ok] == []
            sub.undeclare()
            errors.undeclare()
        finally:
            mallory.close()
        # the victim's stream goes on untouched: its next frame registers, the stored trajectory has 5 poses
        c.step(scene[4])
        assert len(c.trajectory().seqs.to_numpy()) == 5 and not c.errors
    with OccVOClient(ep, "victim", timeout=60, session=open_session(ep, base=logins.session_file("mallory", folder)),
                     login="mallory") as m:  # fmt: skip
        assert m.stream == "mallory.victim"  # mallory's own "victim" is another stream
        m.reset()
        assert m.step(scene[0]).seq == 0


def test_a_login_added_while_serve_runs_works_and_a_removed_one_is_refused(served, scene):
    path = _added(served, "robot1")
    env = _env(OCCVO_ZENOH_CONFIG=str(path))
    got = _occvo("replay", "synthetic:5", "--frames", "6", "--stream", "car0", "--connect", served["endpoint"],
                 "--json", "--quiet", env=env, timeout=300)  # fmt: skip
    assert got.returncode == 0, got.stderr
    summary = json.loads(got.stdout)
    assert summary["stream"] == "robot1.car0" and summary["poses"] == 6
    assert "robot1" in _occvo("logins", "list").stdout
    kept = served["tmp"] / "robot1.json5"  # as the robot keeps it: `occvo logins remove` deletes the folder's copy
    kept.write_text(path.read_text())
    assert _occvo("logins", "remove", "robot1").returncode == 0 and not path.exists()
    deadline = time.monotonic() + 30
    while True:
        try:
            s = zenoh.open(zenoh_config("client", connect=served["endpoint"], base=kept))
        except zenoh.ZError:
            break  # refused: the router took the removal
        s.close()
        assert time.monotonic() < deadline, "a removed login still opens sessions after 30 s"
        time.sleep(0.5)


def test_anonymous_serve_behaves_as_before(tmp_path, scene, uninterrupted):
    proc, ep, err = _serve(tmp_path, "--anonymous")
    try:
        zenoh.open(zenoh_config("client", connect=ep, base=None)).close()  # no login needed
        with OccVOClient(ep, "car0", timeout=60) as c:  # the user's login files exist: dropped, as the router refuses
            assert c.login is None and c.stream == "car0"
            out = replay(c, scene, window=4, timeout=120)
            assert out["poses"] == len(scene)
            for seq, pose in c.poses.items():
                assert (pose.matrix() == uninterrupted[seq]).all()
    finally:
        _stop(proc, err)


@pytest.mark.parametrize("anonymous", [False, True])
def test_occvo_up_has_the_same_default_and_its_anonymous_key(tmp_path, scene, anonymous):
    ep = f"tcp/127.0.0.1:{free_port()}"
    workers = [{"role": r, "config": f"{r}.json5"} for r in ("inference", "registration", "map")]
    for w in workers:  # the built-in worker configs, beside the file
        name = "map_service.json5" if w["role"] == "map" else f"{w['role']}_worker.json5"
        (tmp_path / w["config"]).write_text((REPO / "services/defaults" / name).read_text())
    (tmp_path / "up.json5").write_text(
        json.dumps({"router": {"listen": ep}, "workers": workers, "anonymous": anonymous})
    )
    err = open(tmp_path / "up.err", "w")  # noqa: SIM115 - closed with the process
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "up", "--json", "--config", str(tmp_path / "up.json5")],
        cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=err, text=True,
    )  # fmt: skip
    try:
        line = {"event": None}
        while line["event"] != "ready":
            text = proc.stdout.readline()
            assert text, (tmp_path / "up.err").read_text()[-2000:]
            line = json.loads(text)
        try:
            zenoh.open(zenoh_config("client", connect=ep, base=None)).close()
            opened = True
        except zenoh.ZError:
            opened = False
        assert opened == anonymous  # a session without a login: refused unless anonymous
        with OccVOClient(ep, "car0", timeout=60) as c:
            assert c.stream == ("car0" if anonymous else f"{logins.default_login()}.car0")
            c.wait_for_workers(timeout=30)
            assert replay(c, scene[:4], window=4, timeout=120)["poses"] == 4
    finally:
        _stop(proc, err)
