"""The router goes away and comes back on the same endpoint: the workers (separate processes) and the client reconnect
by themselves (occvo_services.sessions.zenoh_config's connect retry) and the trajectory goes on where it was: every pose,
before and after, equals the offline run of the same frames."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from occvo_services.client import OccVOClient
from occvo_services.local import WORKERS, wait_alive
from occvo_services.sessions import free_port, open_session

REPO = Path(__file__).resolve().parents[2]
warnings.filterwarnings("ignore", category=RuntimeWarning)


def _router(ep: str, log) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "occvo_services.router", "--config", str(REPO / "deploy/router.json5"), "--listen", ep],
        cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        stderr=log,
    )


def _wait_ready(log_path: Path, n: int, timeout: float = 30) -> None:
    """Until the router log holds its n-th "router ready" line."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log_path.read_text().count('"router ready"') >= n:
            return
        time.sleep(0.05)
    raise TimeoutError(f"router not ready: {log_path.read_text()}")


def test_workers_and_client_reconnect_after_router_restart(tmp_path):
    from occvo_core import OccVO
    from occvo_services.commands.replay import load_scene

    ep = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    rlog_path = tmp_path / "router.log"
    rlog = open(rlog_path, "w")
    router = _router(ep, rlog)
    workers = {}
    try:
        _wait_ready(rlog_path, 1)
        for role, module in WORKERS.items():
            workers[role] = subprocess.Popen(
                [sys.executable, "-m", module, "--connect", ep, "--worker-id", f"{role}-rr"],
                cwd=REPO,
                env=env,
                stderr=open(tmp_path / f"{role}.log", "w"),
            )
        scene = load_scene("synthetic:5", frames=6)  # the offline poses, while the workers start
        want = OccVO()
        want.reset()
        for i in range(6):
            want.step(scene[i])
        probe = open_session(ep)
        wait_alive(probe, WORKERS, timeout=60)
        with OccVOClient(ep, "rr", timeout=30) as client:
            client.reset()
            before = [client.step(scene[i]) for i in range(3)]

            router.send_signal(signal.SIGKILL)  # no goodbye: the links just drop
            router.wait()
            time.sleep(1.0)
            router = _router(ep, rlog)
            _wait_ready(rlog_path, 2)
            t0 = time.monotonic()
            wait_alive(probe, WORKERS, timeout=20)  # the workers' liveliness tokens are back on the new router
            print(f"\nrouter killed and restarted: workers seen alive {time.monotonic() - t0:.2f} s after it was up")
            after = [client.step(scene[i]) for i in range(3, 6)]
        probe.close()
        assert [p.seq for p in before + after] == list(range(6))
        got = np.array([p.matrix() for p in before + after])
        assert np.abs(got - want.poses).max() <= 1e-9
        assert all(w.poll() is None for w in workers.values()), "a worker died with the router"
        events = [json.loads(x) for x in (tmp_path / "registration.log").read_text().splitlines() if x.startswith("{")]
        assert not [e for e in events if e["event"] == "error"], events
    finally:
        for w in workers.values():
            if w.poll() is None:
                w.send_signal(signal.SIGTERM)
        codes = {}
        for r, w in workers.items():
            try:
                codes[r] = w.wait(timeout=30)
            except subprocess.TimeoutExpired:
                w.kill()
                codes[r] = w.wait()
        if router.poll() is None:
            router.send_signal(signal.SIGTERM)
            try:
                router.wait(timeout=30)
            except subprocess.TimeoutExpired:
                router.kill()
                router.wait()
        rlog.close()
    assert codes == {r: 0 for r in WORKERS}
