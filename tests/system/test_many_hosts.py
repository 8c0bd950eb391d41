"""Many hosts on one machine: two routers in a mesh on loopback, each with its own registration worker (placement
"members", real subprocesses), one PostgreSQL store shared by both (a real server, tests/pg.py). Four streams go
through; every pose equals offline OccVO's bit for bit, also when a worker is killed (-9) mid-drive and its streams
move to the other, and a paused owner that comes back writes nothing over its streams' new owner."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import zenoh

from occvo_core import OccVO
from occvo_core.sim import SyntheticScene
from occvo_schemas import keys
from occvo_services.client import OccVOClient
from occvo_services.local import REPO, wait_alive
from occvo_services.sessions import free_port, open_router, open_session, zenoh_config

warnings.filterwarnings("ignore", category=RuntimeWarning)
STREAMS, FRAMES, LEASE_S = 4, 12, 3.0


class TwoHosts:
    """Router A (inference worker, registration worker a) and router B (registration worker b, map service) in a
    mesh; the registration workers share the PostgreSQL store."""

    def __init__(self, tmp: Path, store_url: str):
        self.tmp, self.store_url = tmp, store_url
        self.a, self.b = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
        self.router_a = open_router(self.a)
        c = zenoh_config("router", listen=self.b)
        c.insert_json5("connect/endpoints", json.dumps([self.a]))
        self.router_b = zenoh.open(c)
        self.procs: dict[str, subprocess.Popen] = {}
        self.spawn("inference", "occvo_services.inference_worker", self.a)
        self.spawn("map", "occvo_services.map_service", self.b)
        for name, endpoint in (("reg-a", self.a), ("reg-b", self.b)):
            self.spawn_registration(name, endpoint)
        probe = open_session(self.a)
        try:
            wait_alive(probe, ["inference", "registration", "map"], 120)
            deadline = time.monotonic() + 120
            while len(self.members(probe)) < 2:
                assert time.monotonic() < deadline, "both registration workers did not come up"
                time.sleep(0.1)
        finally:
            probe.close()

    @staticmethod
    def members(session) -> set[str]:
        return {str(r.ok.key_expr) for r in session.liveliness().get(keys.registration_shard(0, 0), timeout=2) if r.ok}

    def spawn(self, name: str, module: str, endpoint: str, *args: str) -> None:
        env = dict(os.environ, PYTHONPATH=str(REPO))
        with open(self.tmp / f"{name}.log", "a") as log:
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", module, "--connect", endpoint, "--worker-id", name, *args],
                cwd=REPO,
                env=env,
                stdout=log,
                stderr=log,
            )

    def spawn_registration(self, name: str, endpoint: str) -> None:
        args = ("--store-url", self.store_url, "--placement", "members", "--lease-s", str(LEASE_S))
        self.spawn(name, "occvo_services.registration_worker", endpoint, *args, "--snapshot-every", "4")

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                if p.returncode is None:
                    os.kill(p.pid, signal.SIGCONT)
                p.kill()
                p.wait(10)
        self.router_b.close()
        self.router_a.close()


@pytest.fixture
def hosts(tmp_path, pg_url):
    h = TwoHosts(tmp_path, pg_url)
    try:
        yield h
    finally:
        h.close()


@pytest.fixture(scope="module")
def drives():
    """Four synthetic drives and each one's offline poses."""
    out = {}
    for i in range(STREAMS):
        scene = SyntheticScene(seed=40 + i, frames=FRAMES)
        frames = [scene[k] for k in range(FRAMES)]
        vo = OccVO()
        out[f"car{i}"] = (frames, np.array([vo.step(f).pose for f in frames]))
    return out


def _drive(endpoint: str, stream: str, frames: list, got: dict, step_done=None) -> None:
    with OccVOClient(endpoint, stream, timeout=120, resend_after=5.0) as c:
        c.reset()
        for k, f in enumerate(frames):
            c.step(f)
            if step_done is not None:
                step_done(stream, k)
        got[stream] = (np.array([c.poses[k].matrix() for k in range(len(frames))]), c.errors)


def _stored(store_url: str, stream: str) -> list:
    from occvo_services.store_api import open_store

    store = open_store(store_url)
    try:
        return store.poses(stream)
    finally:
        store.close()


def test_two_workers_on_two_routers_share_the_streams_and_give_offline_poses(hosts, drives):
    got: dict = {}
    threads = [
        threading.Thread(target=_drive, args=(hosts.a if i % 2 else hosts.b, s, frames, got))
        for i, (s, (frames, _)) in enumerate(drives.items())
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    owners = set()
    for stream, (_, want) in drives.items():
        poses, errors = got[stream]
        assert not errors and np.array_equal(poses, want), stream
        assert [p.seq for p in _stored(hosts.store_url, stream)] == list(range(FRAMES))
        owners.add(keys.owner_of(stream, {"reg-a", "reg-b"}))
    assert owners == {"reg-a", "reg-b"}  # both took streams


def test_kill9_of_a_worker_moves_its_streams_and_no_pose_is_lost(hosts, drives):
    victim = "reg-a"
    moved = [s for s in drives if keys.owner_of(s, {"reg-a", "reg-b"}) == victim]
    assert moved, "no stream owned by the victim: choose other stream names"
    killed, half = threading.Event(), FRAMES // 2

    def step_done(stream: str, k: int) -> None:
        if stream == moved[0] and k == half and not killed.is_set():
            hosts.procs[victim].kill()  # SIGKILL: no snapshot, no lease given back
            killed.set()

    got: dict = {}
    threads = [
        threading.Thread(target=_drive, args=(hosts.a, s, frames, got, step_done)) for s, (frames, _) in drives.items()
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert killed.is_set()
    for stream, (_, want) in drives.items():
        poses, _ = got[stream]
        assert np.array_equal(poses, want), stream  # every pose, bit for bit, across the move
        stored = _stored(hosts.store_url, stream)
        assert [p.seq for p in stored] == list(range(FRAMES))
        assert np.array_equal(np.array([p.pose for p in stored]), want)


def test_a_paused_owner_writes_nothing_after_its_streams_moved(hosts, drives):
    """SIGSTOP past the lease: the other worker takes the streams (epoch + 1) and drives them on; SIGCONT: the paused
    worker's frames in hand are fenced (FencedError in its commit), so the store holds only the new owner's poses."""
    from occvo_services.store_api import open_store

    victim = "reg-a"
    stream = next(s for s in drives if keys.owner_of(s, {"reg-a", "reg-b"}) == victim)
    frames, want = drives[stream]
    half = FRAMES // 2
    with OccVOClient(hosts.a, stream, timeout=120, resend_after=2.0) as c:
        c.reset()
        for f in frames[:half]:
            c.step(f)
        os.kill(hosts.procs[victim].pid, signal.SIGSTOP)
        c.publish(frames[half])  # reaches the paused worker too: in hand when it wakes
        time.sleep(LEASE_S + 1.0)
        for f in frames[half + 1 :]:
            c.publish(f)
        c.wait_pose(FRAMES - 1, timeout=120)  # the other worker took the stream and drove it on
        store = open_store(hosts.store_url)
        epoch_after_move = next(lease.epoch for lease in store.leases() if lease.stream == stream)
        assert store.owner_of(stream) == "reg-b"
        os.kill(hosts.procs[victim].pid, signal.SIGCONT)
        time.sleep(3.0)  # it wakes, tries its commits, is refused
        stored = store.poses(stream)
        assert [p.seq for p in stored] == list(range(FRAMES))
        assert np.array_equal(np.array([p.pose for p in stored]), want)
        assert np.array_equal(np.array([c.poses[k].matrix() for k in range(FRAMES)]), want)
        assert next(lease.epoch for lease in store.leases() if lease.stream == stream) >= epoch_after_move
        store.close()
    log = (hosts.tmp / f"{victim}.log").read_text()
    assert "FencedError" in log or "moved to another worker" in log or '"stream_busy"' in log or "handed over" in log
