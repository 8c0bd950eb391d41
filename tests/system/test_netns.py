"""Two hosts on one machine: the router in one network namespace, the workers and the replay client in another,
joined by a veth pair (a real IP link, no loopback shortcut). A synthetic scene replayed across it (`occvo replay`,
its poses followed by `occvo poses --follow`) gives exactly the trajectory of the same replay on loopback."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from occvo_services.client import OccVOClient
from occvo_services.local import WORKERS, InProcessService
from occvo_services.sessions import free_port

REPO = Path(__file__).resolve().parents[2]
SCENE, FRAMES = "synthetic:3", 6
warnings.filterwarnings("ignore", category=RuntimeWarning)


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise OSError(f"`ip {' '.join(args)}` failed: {r.stderr.strip() or r.returncode}")


@pytest.fixture
def two_hosts():
    """(namespace of the router, its address, namespace of the workers); both deleted afterwards."""
    if shutil.which("ip") is None:
        pytest.skip("`ip` (iproute2) not found: cannot make network namespaces")
    tag = os.getpid() % 100000
    ns_r, ns_w = f"occvo-r{tag}", f"occvo-w{tag}"
    veth_r, veth_w = f"ovr{tag}", f"ovw{tag}"
    net = f"10.213.{tag % 250}"
    made = []
    try:
        for ns in (ns_r, ns_w):
            _ip("netns", "add", ns)
            made.append(ns)
        _ip("link", "add", veth_r, "type", "veth", "peer", "name", veth_w)
        _ip("link", "set", veth_r, "netns", ns_r)
        _ip("link", "set", veth_w, "netns", ns_w)
        for ns, dev, host in ((ns_r, veth_r, 1), (ns_w, veth_w, 2)):
            _ip("-n", ns, "addr", "add", f"{net}.{host}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        if shutil.which("ping"):  # the link carries packets (ip netns exec works, the route is there)
            _ip("netns", "exec", ns_w, "ping", "-c", "1", "-W", "2", f"{net}.1")
        else:
            _ip("netns", "exec", ns_w, "true")
    except OSError as exc:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        pytest.skip(f"cannot make network namespaces here: {exc}")
    try:
        yield ns_r, f"{net}.1", ns_w
    finally:
        for ns in made:  # deleting a namespace deletes its end of the veth pair, and so the pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


def _in(ns: str, *cmd: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, *cmd]


def test_router_and_workers_in_separate_network_namespaces(two_hosts, tmp_path):
    from occvo_services.commands.replay import load_scene, replay

    ns_r, addr, ns_w = two_hosts
    ep = f"tcp/{addr}:{free_port()}"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    procs: list[subprocess.Popen] = []

    def start(ns, name, *cmd, **kw):
        procs.append(
            subprocess.Popen(
                _in(ns, *cmd), cwd=REPO, env=env, **(kw or {"stderr": open(tmp_path / f"{name}.log", "w")})
            )
        )
        return procs[-1]

    try:
        router = start(ns_r, "router", "-m", "occvo_services.router", "--listen", ep)
        scene = load_scene(SCENE, FRAMES)
        deadline = time.monotonic() + 30  # sessions open only once the router listens (client connect does not wait)
        while '"router ready"' not in (tmp_path / "router.log").read_text():
            assert router.poll() is None and time.monotonic() < deadline, (tmp_path / "router.log").read_text()
            time.sleep(0.05)
        for role, module in WORKERS.items():
            start(ns_w, role, "-m", module, "--connect", ep, "--worker-id", f"{role}-ns")
        follow = start(
            ns_w,
            "poses",
            "-m",
            "occvo_cli",
            "poses",
            "--follow",
            "--count",
            str(FRAMES),
            "--stream",
            "ns",
            "--connect",
            ep,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        # the same replay on loopback, in this process's namespace, while the namespaced processes start
        with InProcessService() as local, OccVOClient(local.endpoint, "ns") as client:
            want = replay(client, scene, window=4, timeout=60)["trajectory"]
        assert len(want) == FRAMES

        # the workers reach the router only over the veth link: nothing listens on the endpoint in this namespace
        assert "following" in follow.stderr.readline()
        r = subprocess.run(
            _in(
                ns_w,
                "-m",
                "occvo_cli",
                "replay",
                SCENE,
                "--json",
                "--quiet",
                "--frames",
                str(FRAMES),
                "--connect",
                ep,
                "--stream",
                "ns",
                "--timeout",
                "60",
            ),
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 0, r.stderr + "".join(
            (tmp_path / f"{n}.log").read_text()[-2000:] for n in ("router", *WORKERS)
        )
        summary = json.loads(r.stdout.strip().splitlines()[-1])
        assert summary["poses"] == summary["frames"] == FRAMES
        out, _ = follow.communicate(timeout=30)
        rows = [json.loads(line) for line in out.splitlines()]
        assert [row["seq"] for row in rows] == list(range(FRAMES))
        got = np.array([row["pose"] for row in rows])
        print(f"\nreplay across network namespaces vs loopback: max pose difference {np.abs(got - want).max():.3e}")
        assert np.abs(got - want).max() <= 1e-9
        assert router.poll() is None
    finally:
        for proc in reversed(procs):  # workers first, then the router
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 30
        codes = []
        for proc in reversed(procs):
            try:
                codes.append(proc.wait(timeout=max(0.1, deadline - time.monotonic())))
            except subprocess.TimeoutExpired:
                proc.kill()
                codes.append(proc.wait())
    assert codes == [0] * len(procs)
