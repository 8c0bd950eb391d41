"""Fault test: kill -9 the registration worker in the middle of a replay and start it again on the same store.

Router in this process on a random loopback port; the inference and registration workers are real subprocesses. The
replay client resends what was in flight; the restarted worker resumes from its snapshot and journal. Done when the
trajectory has every frame, its APE RMSE is within 5% of an uninterrupted run (measured: equal bit for bit), and every
pose the client received is in the store with the same values."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from occvo_core import OccVO
from occvo_core.eval import ape_rmse
from occvo_schemas import keys
from occvo_services.client import OccVOClient, ServiceError
from occvo_services.commands.replay import replay
from occvo_services.local import REPO, wait_alive
from occvo_services.sessions import free_port, open_router, open_session
from occvo_services.store.sqlite import TrajectoryStore

warnings.filterwarnings("ignore", category=RuntimeWarning)
DATA = Path(__file__).resolve().parents[3] / "shared/data/occvo-sample"
SCENE = DATA / "occupancy/scene-0101"


def _spawn(module: str, endpoint: str, worker_id: str, log: Path, *args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    with open(log, "a") as err:
        return subprocess.Popen(
            [sys.executable, "-m", module, "--connect", endpoint, "--worker-id", worker_id, *args],
            cwd=REPO,
            env=env,
            stdout=err,
            stderr=err,
        )


def _stop(procs: dict, router) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.kill()
            p.wait(10)
    router.close()


def _kill9_run(tmp_path: Path, frames: list, gt: np.ndarray, seed: int, capsys) -> None:
    n = len(frames)
    store_path = tmp_path / "state.sqlite"
    reg_args = ("--store-path", str(store_path), "--snapshot-every", "5", "--working-radius-m", "120")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    log = tmp_path / "registration.log"
    procs = {
        "inference": _spawn("occvo_services.inference_worker", endpoint, "inference-k9", tmp_path / "inference.log"),
        "registration": _spawn("occvo_services.registration_worker", endpoint, "registration-k9", log, *reg_args),
    }
    offline = {}

    def uninterrupted():  # the same frames through OccVO without a stop (the service reproduces it bit for bit)
        vo = OccVO()
        for f in frames:
            vo.step(f)
        offline["poses"] = vo.poses

    try:
        probe = open_session(endpoint)
        wait_alive(probe, ["inference", "registration"], 60)
        probe.close()
        kill_after = int(np.random.default_rng(seed).integers(3, n - 4))  # poses received before the kill
        with OccVOClient(endpoint, "k9", timeout=60, resend_after=5.0) as client:
            out = {}
            replayer = threading.Thread(target=lambda: out.update(replay(client, frames, window=4, timeout=90)))
            replayer.start()
            deadline = time.monotonic() + 60
            while len(client.poses) < kill_after and time.monotonic() < deadline and replayer.is_alive():
                time.sleep(0.005)
            procs["registration"].kill()  # SIGKILL: no snapshot, no goodbye
            procs["registration"].wait(10)
            killed_at = len(client.poses)
            procs["registration"] = _spawn(
                "occvo_services.registration_worker", endpoint, "registration-k9", log, *reg_args
            )
            reference = threading.Thread(target=uninterrupted)
            reference.start()
            replayer.join(120)
            reference.join(120)
            assert not replayer.is_alive() and "poses" in out, "replay did not finish"
            assert out["poses"] == n and sorted(client.poses) == list(range(n)), sorted(client.poses)
            assert out["resends"] > 0 and not client.errors, [e.message for e in client.errors]
            traj = client.trajectory()
            assert traj.seqs.to_numpy().tolist() == list(range(n))
            got = traj.poses.to_numpy()
            received = np.array([client.poses[i].matrix() for i in range(n)])
            assert np.array_equal(received, got)

        store = TrajectoryStore(store_path)
        stored = store.poses("k9")
        store.close()
        assert [p.seq for p in stored] == list(range(n))
        assert np.array_equal(np.array([p.pose for p in stored]), received)  # every published pose, same values

        rmse_cut, rmse_ref = ape_rmse(gt, got), ape_rmse(gt, offline["poses"])
        diff = float(np.abs(got - offline["poses"]).max())
        with capsys.disabled():
            print(
                f"\nkill -9 after {killed_at} poses of {n}: APE RMSE {rmse_cut:.4f} m vs uninterrupted {rmse_ref:.4f} m, "
                f"max pose difference {diff:.3e}, {out['resends']} frames resent"
            )
        assert rmse_cut <= 1.05 * rmse_ref + 1e-9
        events = log.read_text()
        assert '"stream resumed"' in events and events.count('"started"') == 2
    finally:
        _stop(procs, router)


def test_kill9_registration_worker_mid_replay_synthetic(tmp_path, capsys):
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=2, frames=16)
    _kill9_run(tmp_path, [scene[i] for i in range(len(scene))], scene.gt_poses, seed=7, capsys=capsys)


@pytest.mark.skipif(not SCENE.is_dir(), reason=f"sample data not found at {SCENE}")
def test_kill9_registration_worker_mid_replay_scene_0101(tmp_path, capsys):
    from occvo_core.datasets.occvo_release import OccVOReleaseScene
    from occvo_core.trajectory import read_trajectory

    scene, n = OccVOReleaseScene(SCENE), 16
    gt = read_trajectory(DATA / "trajectory/scene-0101.kitti")[:n]
    _kill9_run(tmp_path, [scene[i] for i in range(n)], gt, seed=11, capsys=capsys)


def test_frames_wait_while_the_inference_worker_is_away_and_none_is_lost(tmp_path, scene, uninterrupted):
    """A frame sent while the inference worker is dead reaches nobody; had the next frame gone out once it was back,
    the registration worker would take it as a gap and the lost frame could never be registered. The client holds
    new frames until the worker is back, resends what it lost, and every pose comes, equal to the offline run."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    procs = {
        "inference": _spawn("occvo_services.inference_worker", endpoint, "inference-k9", tmp_path / "inference.log"),
        "registration": _spawn("occvo_services.registration_worker", endpoint, "registration-k9", tmp_path / "r.log"),
    }
    n, k = len(scene), 4
    back = threading.Event()
    probe = None

    def send():  # frame k while the worker is away, the rest once it is back
        client.publish(scene[k])
        back.wait(60)
        for i in range(k + 1, n):
            client.publish(scene[i])

    try:
        probe = open_session(endpoint)
        wait_alive(probe, ["inference", "registration"], 60)
        with OccVOClient(endpoint, "held", timeout=60, resend_after=5.0) as client:
            client.reset()
            for i in range(k):
                client.step(scene[i])
            procs["inference"].kill()
            procs["inference"].wait(10)
            deadline = time.monotonic() + 30
            while any(r.ok for r in probe.liveliness().get(keys.alive("inference"), timeout=2.0)):
                assert time.monotonic() < deadline, "the router still lists the killed inference worker"
                time.sleep(0.05)
            sender = threading.Thread(target=send)
            sender.start()
            time.sleep(0.5)
            procs["inference"] = _spawn(
                "occvo_services.inference_worker", endpoint, "inference-k9b", tmp_path / "inference.log"
            )
            wait_alive(probe, ["inference"], 60)
            back.set()
            sender.join(60)
            assert not sender.is_alive()
            for i in range(k, n):
                try:
                    client.wait_pose(i, timeout=20)
                except ServiceError:
                    break
            assert sorted(client.poses) == list(range(n)) and not client.errors, [
                f"{e.seq} {e.code}: {e.message}" for e in client.errors
            ]
            got = np.array([client.poses[i].matrix() for i in range(n)])
        assert np.allclose(got, np.array(uninterrupted), atol=1e-9)
    finally:
        if probe is not None:
            probe.close()
        _stop(procs, router)
