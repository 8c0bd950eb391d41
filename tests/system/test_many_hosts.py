"""Many hosts on one machine: two routers in a mesh on loopback, each with its own registration worker (placement
"members", real subprocesses), one PostgreSQL store shared by both (a real server, services/store/pg_local.py). Four streams go
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
    from occvo_services.store.factory import open_store

    store = open_store(store_url)
    try:
        return store.poses(stream)
    finally:
        store.close()


def _owner(store_url: str, stream: str) -> str | None:
    from occvo_services.store.factory import open_store

    store = open_store(store_url)
    try:
        return store.owner_of(stream)
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
        owners.add(_owner(hosts.store_url, stream))
    assert owners == {"reg-a", "reg-b"}  # both took streams (the least loaded takes a new one)


def test_kill9_of_a_worker_moves_its_streams_and_no_pose_is_lost(hosts, drives):
    killed, half = [], FRAMES // 2
    first = next(iter(drives))

    def step_done(stream: str, k: int) -> None:
        if stream == first and k == half and not killed:
            victim = _owner(hosts.store_url, stream)
            hosts.procs[victim].kill()  # SIGKILL: no snapshot, no lease given back
            killed.append(victim)

    got: dict = {}
    threads = [
        threading.Thread(target=_drive, args=(hosts.a, s, frames, got, step_done)) for s, (frames, _) in drives.items()
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    (victim,) = killed
    survivor = ({"reg-a", "reg-b"} - {victim}).pop()
    for stream, (_, want) in drives.items():
        poses, _ = got[stream]
        assert np.array_equal(poses, want), stream  # every pose, bit for bit, across the move
        stored = _stored(hosts.store_url, stream)
        assert [p.seq for p in stored] == list(range(FRAMES))
        assert np.array_equal(np.array([p.pose for p in stored]), want)
        assert _owner(hosts.store_url, stream) == survivor


def test_a_paused_owner_writes_nothing_after_its_streams_moved(hosts, drives):
    """SIGSTOP past the lease: the other worker takes the stream (epoch + 1) and drives it on; SIGCONT: whatever the
    paused worker still held is fenced (the next test makes that case), so the store holds exactly the offline poses
    and the stream stays with its new owner."""
    from occvo_services.store.factory import open_store

    stream = next(iter(drives))
    frames, want = drives[stream]
    half = FRAMES // 2
    with OccVOClient(hosts.a, stream, timeout=120, resend_after=2.0) as c:
        c.reset()
        for f in frames[:half]:
            c.step(f)
        victim = _owner(hosts.store_url, stream)
        new_owner = ({"reg-a", "reg-b"} - {victim}).pop()
        os.kill(hosts.procs[victim].pid, signal.SIGSTOP)
        c.publish(frames[half])  # reaches the paused worker too: in hand when it wakes
        time.sleep(LEASE_S + 1.0)
        for f in frames[half + 1 :]:
            c.publish(f)
        c.wait_pose(FRAMES - 1, timeout=120)  # the other worker took the stream and drove it on
        store = open_store(hosts.store_url)
        epoch_after_move = next(lease.epoch for lease in store.leases() if lease.stream == stream)
        assert store.owner_of(stream) == new_owner
        os.kill(hosts.procs[victim].pid, signal.SIGCONT)
        probe = open_session(hosts.a)
        deadline = time.monotonic() + 60
        while len(TwoHosts.members(probe)) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)  # back on the network: what it held has been tried by now
        probe.close()
        time.sleep(1.0)
        stored = store.poses(stream)
        assert [p.seq for p in stored] == list(range(FRAMES))
        assert np.array_equal(np.array([p.pose for p in stored]), want)
        assert np.array_equal(np.array([c.poses[k].matrix() for k in range(FRAMES)]), want)
        assert next(lease.epoch for lease in store.leases() if lease.stream == stream) == epoch_after_move
        assert store.owner_of(stream) == new_owner
        store.close()


def test_a_worker_whose_lease_moved_on_writes_and_publishes_nothing(tmp_path, pg_url, drives):
    """Fencing, made rather than timed: the stream's lease is taken from the worker as a new owner takes a lost one's
    (epoch + 1) while the worker still believes it owns the stream. Its next frame's commit is refused inside the
    commit's transaction: nothing stored, no pose published, the frame left to the new owner."""
    from occvo_services.inference_worker import InferenceWorker
    from occvo_services.registration_worker import RegistrationWorker
    from occvo_services.runtime import WorkerConfig
    from occvo_services.store.factory import open_store

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    base = {"connect": endpoint, "log_level": "WARNING"}
    reg = RegistrationWorker(WorkerConfig(**base, worker_id="reg-f", store_url=pg_url, placement="members")).start()
    inference = InferenceWorker(WorkerConfig(**base, worker_id="inference-f")).start()
    store = open_store(pg_url)
    try:
        stream, (frames, want) = next(iter(drives.items()))
        with OccVOClient(endpoint, stream, timeout=120, resend_after=None) as c:
            c.reset()
            got = [c.step(f).matrix() for f in frames[:3]]
            assert np.array_equal(np.array(got), want[:3])
            epoch = store.acquire(stream, "reg-new", 60.0, take_from="reg-f")  # as a new owner takes a lost one's
            assert epoch == 2 and reg.owns(stream)  # the worker still believes the stream is its own
            c.publish(frames[3])
            deadline = time.monotonic() + 120
            while not reg.stats.snapshot()[0].get("fenced") and time.monotonic() < deadline:
                time.sleep(0.01)
            reg.drain()
            assert reg.stats.snapshot()[0]["fenced"] == 1 and 3 not in c.poses and not c.errors
        assert [p.seq for p in store.poses(stream)] == [0, 1, 2]
        assert store.owner_of(stream) == "reg-new"
    finally:
        store.close()
        inference.stop()
        reg.stop()
        router.close()
