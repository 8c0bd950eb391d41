"""`occvo serve` keeps its workers running: any worker (inference, registration, map service) killed with SIGKILL in
the middle of a replay is started again (new pid, the `crashed` event in the log) and the replay completes with every
pose, equal to the offline run; a restarted map service answers from its store. A listen endpoint beyond loopback
without authentication (--anonymous) is refused unless --insecure."""

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
import pytest

from occvo_core.errors import ConfigError
from occvo_services.client import OccVOClient, ServiceError
from occvo_services.commands._common import check_listen_secure, deploy_dir, is_loopback
from occvo_services.commands.replay import replay
from occvo_services.sessions import free_port

REPO = Path(__file__).resolve().parents[2]
DEPLOY = deploy_dir()


def test_non_loopback_listen_needs_authentication_or_insecure():
    assert is_loopback("tcp/127.0.0.1:7447") and is_loopback("tcp/[::1]:7447") and not is_loopback("tcp/0.0.0.0:7447")
    with pytest.raises(ConfigError, match="without authentication"):
        check_listen_secure(DEPLOY / "router.json5", ["tcp/0.0.0.0:7447"], insecure=False)
    check_listen_secure(DEPLOY / "router.json5", ["tcp/0.0.0.0:7447"], insecure=True)
    check_listen_secure(DEPLOY / "router.json5", ["tcp/127.0.0.1:7447"], insecure=False)
    check_listen_secure(DEPLOY / "acl/router.json5", ["tcp/0.0.0.0:7447"], insecure=False)  # user/password
    check_listen_secure(DEPLOY / "tls/router.json5", ["tls/0.0.0.0:7447"], insecure=False)  # mutual TLS
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    rc = subprocess.run(
        # the anonymous mode: the default's router has logins and access control (tests/system/test_serve_logins.py)
        [sys.executable, "-m", "occvo_cli", "serve", "--anonymous", "--listen", f"tcp/0.0.0.0:{free_port()}"],
        check=False,
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert rc.returncode != 0 and "without authentication" in rc.stderr and "--insecure" in rc.stderr


@pytest.mark.parametrize("role", ["registration", "inference", "map"])
def test_serve_restarts_a_worker_killed_mid_replay_and_no_pose_is_lost(role, tmp_path, scene, uninterrupted):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    err = open(tmp_path / "serve.log", "w")  # noqa: SIM115 - closed in finally, after the process
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "occvo_cli",
            "serve",
            "--listen",
            endpoint,
            "--json",
            "--store-path",
            str(tmp_path / "occvo.sqlite"),
            "--log-dir",
            str(tmp_path),
        ],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
    )
    try:
        ready = json.loads(proc.stdout.readline())
        while ready["event"] != "ready":  # listening, then each worker as it comes up
            ready = json.loads(proc.stdout.readline())
        assert ready["event"] == "ready" and set(ready["workers"]) == {"inference", "registration", "map"}
        victim = ready["workers"][role]
        n = len(scene)
        with OccVOClient(endpoint, "served", timeout=60, resend_after=5.0) as client:
            out = {}
            replayer = threading.Thread(target=lambda: out.update(replay(client, scene, window=4, timeout=120)))
            replayer.start()
            deadline = time.monotonic() + 60
            while len(client.poses) < 3 and time.monotonic() < deadline:
                time.sleep(0.005)
            os.kill(victim, signal.SIGKILL)
            replayer.join(180)
            assert not replayer.is_alive() and out.get("poses") == n, [
                f"{e.seq} {e.code}: {e.message}" for e in client.errors
            ]
            assert sorted(client.poses) == list(range(n)) and not client.errors, [e.message for e in client.errors]
            got = np.array([client.poses[i].matrix() for i in range(n)])
            if role == "map":  # back, serving what its store holds (updates sent while it was away are lost)
                deadline = time.monotonic() + 60
                while True:
                    try:
                        assert client.map_info().tile_count > 0
                        break
                    except ServiceError:  # not up again yet
                        assert time.monotonic() < deadline
                        time.sleep(0.2)
        assert np.allclose(got, np.array(uninterrupted), atol=1e-9)
        proc.send_signal(signal.SIGINT)
        stdout, _ = proc.communicate(timeout=90)
        assert proc.returncode == 0
        assert json.loads(stdout.strip().splitlines()[-1]) == {
            "event": "stopped",
            "exit_codes": {"inference": 0, "registration": 0, "map": 0},
        }
        events = [
            json.loads(line) for line in (tmp_path / "serve.log").read_text().splitlines() if line.startswith("{")
        ]
        crashed = [e for e in events if e["event"] == "crashed"]
        assert len(crashed) == 1 and crashed[0]["name"] == role and crashed[0]["how"] == "signal SIGKILL"
        restarted = [e for e in events if e["event"] == "started" and e["name"] == role]
        assert len(restarted) == 2 and restarted[1]["pid"] != victim
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        err.close()
