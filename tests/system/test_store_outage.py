"""`occvo serve` on a PostgreSQL store with the database stopped mid-drive for longer than the client's
`resend_after`: the frames the worker cannot store are answered `store_unavailable` (not an answer: the client sends
them again), and once the database is back every stream goes on with every pose, stored and equal to an offline
run's."""

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

from occvo_services.sessions import free_port
from occvo_services.store.url import STORE_URL_ENV

REPO = Path(__file__).resolve().parents[2]
STREAMS = ("car0", "car1")


def serve(tmp_path: Path, url: str, *args: str) -> tuple[subprocess.Popen, str]:
    """`occvo serve` on the store `url` (given in OCCVO_STORE_URL) with `args`, once ready: the process, its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    env[STORE_URL_ENV] = url
    err = open(tmp_path / "serve.err", "w")  # noqa: SIM115 - the process holds it; closed with the test's tmp dir
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "serve", "--listen", endpoint, "--json", "--log-dir", str(tmp_path), *args],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
    )
    while True:
        line = proc.stdout.readline()
        assert line, (tmp_path / "serve.err").read_text()
        if json.loads(line)["event"] == "ready":
            return proc, endpoint


def drive_through_outage(endpoint: str, scene: list, outage, down_at: int, timeout: float) -> dict:
    """Each stream of STREAMS driven by its own client, one frame at a time; `outage()` runs once every stream has
    its pose `down_at` (the database stopped and started again meanwhile). The poses and error events of each."""
    from occvo_services.client import OccVOClient

    reached, out = threading.Barrier(len(STREAMS) + 1), {}

    def drive(stream: str) -> None:
        with OccVOClient(endpoint, stream, timeout=timeout) as c:
            c.reset()
            poses = []
            for i, frame in enumerate(scene):
                if i == down_at + 1:
                    reached.wait()  # the outage starts now: the next frames are sent into it
                poses.append(c.step(frame).matrix())
            out[stream] = (poses, list(c.errors), c.resends, c.stream)  # c.stream: with its login's prefix

    threads = [threading.Thread(target=drive, args=(s,)) for s in STREAMS]
    for t in threads:
        t.start()
    reached.wait(timeout=timeout)
    outage()
    for t in threads:
        t.join(timeout=timeout)
    return out


def test_a_database_outage_past_resend_after_loses_no_pose(tmp_path, pg_cluster, pg_url, scene, uninterrupted):
    proc, endpoint = serve(tmp_path, pg_url)

    def outage() -> None:
        pg_cluster.stop()
        time.sleep(8.0)
        pg_cluster.start()

    try:
        got = drive_through_outage(endpoint, scene, outage, down_at=4, timeout=120)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
    assert proc.returncode == 0
    from occvo_services.store.factory import open_store

    store = open_store(pg_url)
    try:
        for stream in STREAMS:
            poses, errors, resends, wire_id = got[stream]
            assert np.array_equal(np.array(poses), np.array(uninterrupted)), stream
            codes = {e.code for e in errors}
            assert "store_unavailable" in codes and codes <= {"store_unavailable", "not_stored", "seq_held"}, codes
            assert resends > 0
            stored = store.poses(wire_id)
            assert [p.seq for p in stored] == list(range(len(scene)))
            assert np.array_equal(np.array([p.pose for p in stored]), np.array(uninterrupted)), stream
    finally:
        store.close()
