"""docs/service.md's "Two routers with certificates" on loopback: the certificates made by the recipe's own commands
in a temporary folder, the shipped deploy/multihost/router-a.json5 and router-b.json5 and session-<role>.json5 with
/etc/occvo/tls and the host names substituted as the recipe tells a user, each router a `python -m
occvo_services.router` process. The three workers (their certificates) on router B and a client login (`camera`) on
router A exchange frames and poses, equal to offline OccVO's; a session without a certificate is refused; a client
login of its own (`camera2`) declares no worker token a worker sees and neither receives, queries nor publishes on
`camera`'s streams. Real processes, real TLS, a real PostgreSQL store (the multihost workers' placement members)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mesh_certs import make_certificates, shipped

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services.client import OccVOClient, camera_frame_of
from occvo_services.local import REPO, wait_alive
from occvo_services.sessions import free_port, open_login, zenoh_config

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not found: cannot make certificates")
MULTIHOST = REPO / "deploy" / "multihost"
FRAMES = 6


def _session(ep: str, config: Path, **inserts) -> zenoh.Session:
    c = zenoh_config("client", connect=ep, base=config)
    for key, value in inserts.items():
        c.insert_json5(key, json.dumps(value))
    return zenoh.open(c)


@pytest.fixture(scope="module")
def mesh(tmp_path_factory, pg_cluster):
    tmp = tmp_path_factory.mktemp("mesh-tls")
    tls = tmp / "tls"
    tls.mkdir()
    make_certificates(tls, ("camera2",))  # a second client login
    pa, pb = free_port(), free_port()
    ep_a, ep_b = f"tls/localhost:{pa}", f"tls/localhost:{pb}"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    procs, logs = [], []

    def start(name, cmd, extra=None):
        log = open(tmp / f"{name}.log", "w")  # noqa: SIM115 - closed at teardown
        logs.append(log)
        procs.append(subprocess.Popen(cmd, cwd=REPO, env={**env, **(extra or {})}, stdout=log, stderr=log))

    router = [sys.executable, "-m", "occvo_services.router", "--config"]
    # router B first: it keeps dialling A, as the recipe says either may start first
    start("router-b", [*router, str(shipped("router-b.json5", tmp, tls)), "--listen", f"tls/127.0.0.1:{pb}",
                       "--connect", ep_a])  # fmt: skip
    start("router-a", [*router, str(shipped("router-a.json5", tmp, tls)), "--listen", f"tls/127.0.0.1:{pa}"])
    sessions = {r: shipped(f"session-{r}.json5", tmp, tls) for r in ("inference", "registration", "map", "camera")}
    (tmp / "session-camera2.json5").write_text(sessions["camera"].read_text().replace("camera", "camera2"))
    sessions["camera2"] = tmp / "session-camera2.json5"
    try:
        deadline = time.monotonic() + 60
        while True:  # router B up (a python process's start) first: its watcher session is made here
            try:
                watcher = _session(ep_b, sessions["registration"])  # a worker's view: the tokens it sees
                break
            except zenoh.ZError:
                assert time.monotonic() < deadline, (tmp / "router-b.log").read_text()[-2000:]
                time.sleep(0.5)
        store = ["--store-url", pg_cluster.new_database()]
        for role, module, config in (
            ("inference", "inference_worker", "inference_worker.json5"),
            ("registration", "registration_worker", "registration_worker_b.json5"),
            ("map", "map_service", "map_service_b.json5"),
        ):
            args = ["--source", "replay"] if role == "inference" else store
            cmd = [sys.executable, "-m", f"occvo_services.{module}", "--config", str(MULTIHOST / config),
                   "--connect", ep_b, "--worker-id", f"{role}-b", *args]  # fmt: skip
            start(role, cmd, {"OCCVO_ZENOH_CONFIG": str(sessions[role])})
        wait_alive(watcher, ("inference", "registration", "map"), timeout=240)
        yield {"a": ep_a, "b": ep_b, "sessions": sessions, "watcher": watcher, "tmp": tmp}
        watcher.close()
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in logs:
            log.close()


def test_a_client_on_router_a_gets_the_poses_of_workers_on_router_b(mesh, scene, uninterrupted):
    session, login = open_login(mesh["a"], mesh["sessions"]["camera"], pick_up=False)
    assert login == "camera"
    with OccVOClient(mesh["a"], "car", timeout=180, session=session, login=login) as c:
        assert c.stream == "camera.car"
        c.reset()
        got = [c.step(f) for f in scene[:FRAMES]]
    session.close()
    poses = np.array([p.matrix() for p in got])
    assert np.array_equal(poses, np.array(uninterrupted[:FRAMES])), "poses through the TLS mesh differ from offline"


def test_a_session_without_a_certificate_is_refused(mesh, tmp_path):
    no_cert = {
        "transport/link/tls/enable_mtls": False,
        "transport/link/tls/connect_certificate": None,
        "transport/link/tls/connect_private_key": None,
    }
    for ep in (mesh["a"], mesh["b"]):
        with pytest.raises(zenoh.ZError):
            _session(ep, mesh["sessions"]["camera"], **no_cert).close()
        with pytest.raises(zenoh.ZError):  # plain tcp on the TLS port
            zenoh.open(zenoh_config("client", connect=ep.replace("tls/", "tcp/"))).close()


def test_a_client_login_declares_no_worker_token(mesh):
    rogue = _session(mesh["a"], mesh["sessions"]["camera2"])
    try:
        tokens = [rogue.liveliness().declare_token(k) for k in (keys.alive("registration", "fake"),
                                                                keys.registration_shard(0, 0, "fake"))]  # fmt: skip
        time.sleep(2.0)
        seen = {str(r.ok.key_expr) for r in mesh["watcher"].liveliness().get("occvo/@shard/**", timeout=3.0) if r.ok}
        seen |= {str(r.ok.key_expr) for r in mesh["watcher"].liveliness().get(keys.alive(), timeout=3.0) if r.ok}
        assert keys.registration_shard(0, 0, "registration-b") in seen, seen  # the real worker's is seen
        assert not [k for k in seen if k.endswith("/fake")], seen
        for t in tokens:
            t.undeclare()
    finally:
        rogue.close()


def test_a_client_login_reads_and_writes_nothing_of_another(mesh, scene):
    session, login = open_login(mesh["a"], mesh["sessions"]["camera"], pick_up=False)
    rogue = _session(mesh["b"], mesh["sessions"]["camera2"])  # on the other router
    ear = _session(mesh["a"], mesh["sessions"]["camera2"])  # on the victim's (a session hears its own puts: another)
    heard = []
    subs = [ear.declare_subscriber(k, heard.append) for k in ("occvo/camera.victim/**", "occvo/**")]
    try:
        with OccVOClient(mesh["a"], "victim", timeout=180, session=session, login=login) as c:
            c.reset()
            for f in scene[:3]:
                c.step(f)
            # camera2's frame on camera's stream: refused by the access control, never registered
            stray = encode(camera_frame_of(scene[5], c.stream, 3))
            for _ in range(5):
                rogue.put(keys.camera(c.stream), stray)
            time.sleep(2.0)
            replies = list(rogue.get(keys.trajectory(c.stream), timeout=3.0))
            replies += list(rogue.get(keys.map_info(c.stream), timeout=3.0))
            traj = c.trajectory()
            assert c.errors == [], c.errors
        assert heard == [], [str(s.key_expr) for s in heard]
        assert replies == []
        assert traj.seqs.to_numpy().tolist() == [0, 1, 2]
    finally:
        for s in subs:
            s.undeclare()
        ear.close()
        rogue.close()
        session.close()
