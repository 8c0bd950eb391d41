"""Placement "members" under the shipped access control (deploy/acl/router.json5): two registration workers (real
processes, both the `registration` login, one PostgreSQL store) see each other's tokens, share the streams of a camera
login and, when the owner of a stream is killed (-9) mid-drive, the other takes its streams: every pose bit-identical
to offline OccVO's and stored, no worker fenced by the other while both live."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from test_many_hosts import FRAMES, LEASE_S, _owner, _stored, drives  # noqa: F401 - drives: a fixture
from test_store_outage import serve

from occvo_schemas import keys
from occvo_services.client import OccVOClient
from occvo_services.local import REPO
from occvo_services.router import router_config
from occvo_services.sessions import ZENOH_CONFIG_ENV, free_port, zenoh_config

DEPLOY = REPO / "deploy"
USERS = ("inference", "registration", "camera")


def _session_file(tmp: Path, user: str) -> Path:
    """The shipped session config of the login, its password set."""
    path = tmp / f"session-{user}.json5"
    path.write_text((DEPLOY / f"acl/session-{user}.json5").read_text().replace("CHANGE-ME", f"pw-{user}"))
    return path


class AclMembers:
    """One router with the shipped ACL; the inference worker and the registration workers reg-a and reg-b, each as
    its login; reg-a and reg-b in placement members on one store."""

    def __init__(self, tmp: Path, store_url: str):
        (tmp / "users.txt").write_text("".join(f"{u}:pw-{u}\n" for u in USERS))
        self.endpoint, self.store_url, self.tmp = f"tcp/127.0.0.1:{free_port()}", store_url, tmp
        rc = router_config(DEPLOY / "acl/router.json5", listen=[self.endpoint])
        rc.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp / "users.txt")))
        self.router = zenoh.open(rc)
        self.files = {u: _session_file(tmp, u) for u in USERS}
        self.procs: dict[str, subprocess.Popen] = {}
        self.spawn("inference", "inference", "occvo_services.inference_worker")
        members = ("--store-url", store_url, "--placement", "members", "--lease-s", str(LEASE_S))
        for name in ("reg-a", "reg-b"):
            self.spawn(name, "registration", "occvo_services.registration_worker", *members, "--snapshot-every", "4")
        deadline = time.monotonic() + 120
        while len(self.alive(keys.registration_shard(0, 0))) < 2 or not self.alive(keys.alive("inference")):
            assert time.monotonic() < deadline, "the workers did not come up"
            time.sleep(0.2)

    def alive(self, selector: str) -> set[str]:
        return {str(r.ok.key_expr) for r in self.router.liveliness().get(selector, timeout=2) if r.ok}

    def spawn(self, name: str, user: str, module: str, *args: str) -> None:
        env = dict(os.environ, PYTHONPATH=str(REPO), **{ZENOH_CONFIG_ENV: str(self.files[user])})
        with open(self.tmp / f"{name}.log", "a") as log:
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", module, "--connect", self.endpoint, "--worker-id", name, *args],
                cwd=REPO,
                env=env,
                stdout=log,
                stderr=log,
            )

    def camera(self) -> zenoh.Session:
        return zenoh.open(zenoh_config("client", connect=self.endpoint, base=self.files["camera"]))

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
                p.wait(10)
        self.router.close()


def _fenced(log: Path) -> int:
    return sum('"fenced: the stream has another owner"' in line for line in log.read_text().splitlines())


def test_members_under_the_shipped_acl_share_streams_and_fail_over_on_kill9(tmp_path, pg_url, drives):  # noqa: F811
    hosts = AclMembers(tmp_path, pg_url)
    streams = {f"camera.{s}": v for s, v in drives.items()}  # the camera login's prefix
    first, half, killed, owners = next(iter(streams)), FRAMES // 2, [], set()
    session = hosts.camera()
    try:

        def step_done(stream: str, k: int) -> None:
            if stream == first and k == half and not killed:
                owners.update(_owner(pg_url, s) for s in streams)  # both took streams while both lived
                victim = _owner(pg_url, stream)
                hosts.procs[victim].kill()  # SIGKILL: no snapshot, no lease given back
                killed.append(victim)

        def drive(stream: str, frames: list, got: dict) -> None:
            with OccVOClient(hosts.endpoint, stream, timeout=120, session=session) as c:
                c.reset()
                for k, f in enumerate(frames):
                    c.step(f)
                    step_done(stream, k)
                got[stream] = np.array([c.poses[k].matrix() for k in range(len(frames))])

        got: dict = {}
        threads = [threading.Thread(target=drive, args=(s, frames, got)) for s, (frames, _) in streams.items()]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
    finally:
        session.close()
        hosts.close()
    (victim,) = killed
    survivor = ({"reg-a", "reg-b"} - {victim}).pop()
    assert owners == {"reg-a", "reg-b"}, owners
    for stream, (_, want) in streams.items():
        assert np.array_equal(got[stream], want), stream  # every pose, bit for bit, across the move
        stored = _stored(pg_url, stream)
        assert [p.seq for p in stored] == list(range(FRAMES))
        assert np.array_equal(np.array([p.pose for p in stored]), want)
        assert _owner(pg_url, stream) == survivor
    assert _fenced(tmp_path / f"{survivor}.log") == 0  # the two saw each other: neither took the other's streams


def test_serve_with_placement_members_shares_the_streams(tmp_path, pg_url, drives):  # noqa: F811
    """`occvo serve --placement members --registration-workers 2` on a PostgreSQL store: both workers take streams,
    every pose bit-identical to offline OccVO's; without a store it is one line, exit 2."""
    proc, endpoint = serve(tmp_path, pg_url, "--placement", "members", "--registration-workers", "2")
    got: dict = {}
    wire: dict = {}  # the stream ids as stored: with the login's prefix serve's clients pick up
    try:

        def drive(stream: str, frames: list) -> None:
            with OccVOClient(endpoint, stream, timeout=120) as c:
                wire[stream] = c.stream
                c.reset()
                got[stream] = np.array([c.step(f).matrix() for f in frames])

        threads = [threading.Thread(target=drive, args=(s, frames)) for s, (frames, _) in drives.items()]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
        owners = {_owner(pg_url, wire[s]) for s in drives}
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
    assert proc.returncode == 0 and len(owners) == 2, owners
    for stream, (_, want) in drives.items():
        assert np.array_equal(got[stream], want), stream
    env = {k: v for k, v in os.environ.items() if k != "OCCVO_STORE_URL"}
    out = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "serve", "--placement", "members"],
        cwd=REPO,
        env={**env, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        "occvo serve: error: --placement members needs a store (--store): the workers hand streams over through it"
    ], out.stderr
