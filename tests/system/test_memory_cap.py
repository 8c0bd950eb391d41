"""The registration worker's memory cap (`max_rss_mb`, services/memory.py), on a real worker process on loopback.

Over 85% of the cap a new stream is refused with one stream_limit error event naming max_rss_mb; over 75% the stream
idle longest is evicted to the store and its next frame resumes it there. One client opening stream after stream
keeps the worker's resident set under the cap, every stream answered (a pose or the refusal), and an evicted stream
goes on with the offline poses. The cap is set from the worker's own resident set at start, so the test does not
depend on this machine's library sizes."""

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
import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import ErrorEvent, OccupancyFrameMsg, PoseEstimate, WorkerHealth
from occvo_services.client import camera_frame_of
from occvo_services.local import REPO, wait_alive
from occvo_services.memory import ADMIT_SHARE, EVICT_IDLE_S, EVICT_SHARE
from occvo_services.sessions import free_port, open_router, open_session

BLOCK = zenoh.CongestionControl.BLOCK
STREAMS = 40  # one-frame streams a client opens, one after the other
PACE_S = 0.25  # between two: streams become idle (EVICT_IDLE_S) while new ones come


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


class Registration:
    """A registration worker process with `max_rss_mb`, and a session watching its poses and error events."""

    def __init__(self, tmp: Path, endpoint: str, max_rss_mb: int, name: str, **config):
        cfg = tmp / f"{name}.json5"
        cfg.write_text(
            json.dumps(
                {
                    "warm_up": True,  # the kernels compiled (or loaded) before the resident set is measured
                    "log_level": "WARNING",
                    "store_path": str(tmp / "occvo.sqlite"),
                    "max_rss_mb": max_rss_mb,
                    "max_streams": 1000,  # the cap is the only limit here
                    "max_streams_per_client": 1000,
                    **config,
                }
            )
        )
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
        self.log = open(tmp / f"{name}.log", "w")  # noqa: SIM115 - closed in stop()
        self.worker_id = f"registration-{name}"
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occvo_services.registration_worker",
                "--connect",
                endpoint,
                "--worker-id",
                self.worker_id,
                "--config",
                str(cfg),
            ],
            cwd=REPO,
            env=env,
            stdout=self.log,
            stderr=self.log,
        )
        self.session = open_session(endpoint)
        self.poses: dict[tuple[str, int], PoseEstimate] = {}
        self.errors: list[ErrorEvent] = []
        self.lock = threading.Lock()
        self.subs = [
            self.session.declare_subscriber(keys.pose("*"), self._on_pose),
            self.session.declare_subscriber(keys.errors("*"), self._on_error),
        ]
        wait_alive(self.session, ["registration"], timeout=120)

    def _on_pose(self, s):
        p = decode(s.payload.to_bytes(), PoseEstimate)
        with self.lock:
            self.poses[(p.stream, p.seq)] = p

    def _on_error(self, s):
        with self.lock:
            self.errors.append(decode(s.payload.to_bytes(), ErrorEvent))

    def send(self, frame, stream: str, seq: int, timeout: float = 60.0) -> str:
        """Publish one occupancy frame and wait for its answer: 'pose' or the error event's code."""
        with self.lock:
            seen = len(self.errors)
        occ = camera_frame_of(frame, stream, seq).gt_occupancy
        msg = OccupancyFrameMsg(stream=stream, seq=seq, stamp=float(frame.stamp), source="replay", occupancy=occ)
        self.session.put(keys.occupancy(stream), encode(msg), congestion_control=BLOCK)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if (stream, seq) in self.poses:
                    return "pose"
                codes = [e.code for e in self.errors[seen:] if e.stream == stream and e.seq == seq]
            if codes:
                return codes[0]
            time.sleep(0.01)
        raise AssertionError(f"no answer to {stream} seq {seq} in {timeout} s")

    def counters(self) -> dict:
        [r] = [r for r in self.session.get(keys.stats(self.worker_id), timeout=10.0) if r.ok is not None]
        return decode(r.ok.payload.to_bytes(), WorkerHealth).counters

    def stop(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self.log.close()


@pytest.fixture
def endpoint():
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    yield ep
    router.close()


def test_memory_cap_refuses_new_streams_and_evicts_idle_ones_to_the_store(tmp_path, endpoint, scene, uninterrupted):
    # a cap the worker is over from the start: every new stream is refused, naming the cap
    w = Registration(tmp_path, endpoint, 64, "over")
    try:
        base = rss_mb(w.proc.pid)
        assert w.send(scene[0], "mc.refused", 0) == "stream_limit"
        [ev] = [e for e in w.errors if e.stream == "mc.refused"]
        assert "max_rss_mb=64" in ev.message, ev.message
        assert ("mc.refused", 0) not in w.poses and w.counters()["streams_refused_memory"] == 1
    finally:
        w.stop()

    # room for a few streams above the worker's own size: idle ones are evicted as new ones come
    cap = int((base + 40) / EVICT_SHARE)
    w = Registration(tmp_path, endpoint, cap, "capped")
    peak, sampling = [0.0], threading.Event()

    def sample():
        while not sampling.wait(0.02):
            peak[0] = max(peak[0], rss_mb(w.proc.pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        answers = {}
        for i in range(STREAMS):
            answers[f"mc.s{i}"] = w.send(scene[0], f"mc.s{i}", 0)
            time.sleep(PACE_S)
        assert set(answers.values()) <= {"pose", "stream_limit"}, answers
        assert answers["mc.s0"] == "pose"
        counters = w.counters()
        assert counters.get("streams_evicted_memory", 0) >= 1, counters
        refused = [e for e in w.errors if e.code == "stream_limit"]
        assert all(f"max_rss_mb={cap}" in e.message for e in refused)
        assert len(refused) == counters.get("streams_refused_memory", 0)
        # the first stream was evicted (idle longest): its next frame resumes it from the store, poses as offline.
        # Refused while the worker is full, it is sent again, as a client resends an unanswered frame; each refusal
        # evicts another idle stream
        for _ in range(10):
            if w.send(scene[1], "mc.s0", 1) == "pose":
                break
            time.sleep(EVICT_IDLE_S)
        assert w.counters()["resumes"] >= 1
        got = [w.poses[("mc.s0", i)].matrix() for i in range(2)]
        assert np.allclose(np.array(got), np.array(uninterrupted[:2]), atol=1e-9)
    finally:
        sampling.set()
        sampler.join()
        w.stop()
    print(f"base {base:.0f} MB, cap {cap} MB, peak {peak[0]:.0f} MB, answers {list(answers.values())}, {counters}")
    assert peak[0] < cap, (peak[0], cap, base, ADMIT_SHARE)
