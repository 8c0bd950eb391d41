"""End to end with the router in this process and the three workers as separate processes
(`python -m occvo_services.<module>`), on a random loopback port: scene-0101 replayed through the service gives the
offline trajectory and map; the CLI commands answer; SIGTERM lets every worker finish its frame and exit 0."""

from __future__ import annotations

import argparse
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

from occvo_core.map_tiles import tiles_from_map
from occvo_services.client import OccVOClient, ServiceError
from occvo_services.local import REPO, LocalService
from occvo_services.sessions import free_port

DATA = Path(__file__).resolve().parents[3] / "shared/data/occvo-sample"
SCENE = DATA / "occupancy/scene-0101"
pytestmark = pytest.mark.skipif(not SCENE.is_dir(), reason=f"sample data not found at {SCENE}")
warnings.filterwarnings("ignore", category=RuntimeWarning)


def _sorted_rows(points, labels):
    a = np.column_stack([points, labels.astype(np.float64)])
    return a[np.lexsort(a.T[::-1])]


def _cli(module, argv):
    import importlib

    mod = importlib.import_module(f"occvo_services.commands.{module}")
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    mod.add_parser(sub)
    return parser.parse_args(argv)


@pytest.mark.slow
def test_scene_0101_through_separate_worker_processes_matches_offline(capsys):
    from occvo_core.datasets import open_scene
    from occvo_core.datasets.occvo_release import OccVOReleaseScene
    from occvo_core.pipeline import OdometryPipeline
    from occvo_services.commands import map_info, poses, replay, tile

    scene = OccVOReleaseScene(SCENE)
    offline = {}

    def run_offline():  # what `occvo run --input SCENE` computes, in parallel with the service (other processes)
        vo = OdometryPipeline(open_scene(SCENE), progress=False).run().odometry
        offline["poses"] = vo.poses
        offline["map"] = vo.map_points()

    service = LocalService(quiet=True)
    try:
        service.start()
        t = threading.Thread(target=run_offline)
        t.start()
        with OccVOClient(service.endpoint, "e2e") as client:
            out = replay.replay(client, scene, window=4)
            assert out["poses"] == len(scene) and not client.errors
            info = client.map_info()
            deadline = time.monotonic() + 30
            while info.last_seq != len(scene) - 1 and time.monotonic() < deadline:
                time.sleep(0.1)
                info = client.map_info()
            tiles = client.region()
            t.join(300)
            diff = np.abs(out["trajectory"] - offline["poses"]).max()
            with capsys.disabled():
                print(f"\nscene-0101 through the service vs occvo run: max pose difference {diff:.3e}")
            assert diff <= 1e-6
            P, L = offline["map"]
            want = tiles_from_map(P, L, 20.0)
            assert {(tl.ix, tl.iy) for tl in tiles} == set(want)
            for tl in tiles:
                p, l = want[(tl.ix, tl.iy)]
                assert np.array_equal(_sorted_rows(tl.points.to_numpy(), tl.labels.to_numpy()), _sorted_rows(p, l))
            assert info.voxel_count == len(P) and info.tile_count == len(want)
            assert [p.status for p in out["pose_msgs"].values()].count("initialised") == 1

            # the CLI commands against the running service
            ep = ["--connect", service.endpoint, "--stream", "e2e"]
            capsys.readouterr()
            assert map_info.run(_cli("map_info", ["map-info", "--json", *ep])) == 0
            assert json.loads(capsys.readouterr().out)["tile_count"] == len(want)
            ix, iy = next(iter(want))
            assert tile.run(_cli("tile", ["tile", str(ix), str(iy), "--json", *ep])) == 0
            assert json.loads(capsys.readouterr().out)["voxels"] == len(want[(ix, iy)][0])
            with pytest.raises(ServiceError, match="tile_not_found"):
                tile.run(_cli("tile", ["tile", "999", "999", *ep]))
            assert poses.run(_cli("poses", ["poses", "--format", "kitti", *ep])) == 0
            rows = np.loadtxt(capsys.readouterr().out.splitlines())
            assert np.abs(rows.reshape(-1, 3, 4) - offline["poses"][:, :3, :4]).max() <= 1e-6

            # SIGTERM while a frame is in the registration worker: it is finished and published, exit codes 0
        with OccVOClient(service.endpoint, "term") as c2:
            c2.reset()
            c2.publish(scene[0])
            time.sleep(0.15)
            codes = service.stop_workers()
            assert codes == {"inference": 0, "registration": 0, "map": 0}
            assert c2.wait_pose(0, timeout=5).status == "initialised"
    finally:
        service.stop()


@pytest.mark.slow
def test_serve_command_starts_and_stops_cleanly(tmp_path):
    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "occvo_cli",
            "serve",
            "--json",
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "--log-dir",
            str(tmp_path),
        ],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        events = [json.loads(proc.stdout.readline())]
        while events[-1]["event"] != "ready":
            events.append(json.loads(proc.stdout.readline()))
        assert events[0] == {"event": "listening", "endpoint": f"tcp/127.0.0.1:{port}"}
        ready = events[-1]
        assert ready["event"] == "ready" and set(ready["workers"]) == {"inference", "registration", "map"}
        follow = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "occvo_cli",
                "poses",
                "--follow",
                "--count",
                "3",
                "--stream",
                "cli",
                "--connect",
                f"tcp/127.0.0.1:{port}",
            ],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert "following" in follow.stderr.readline()
        rc = subprocess.run(
            [
                sys.executable,
                "-m",
                "occvo_cli",
                "replay",
                str(SCENE),
                "--json",
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "--frames",
                "3",
                "--stream",
                "cli",
            ],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert rc.returncode == 0, rc.stderr
        summary = json.loads(rc.stdout.strip().splitlines()[-1])
        assert summary["poses"] == 3 and summary["frames"] == 3
        followed, _ = follow.communicate(timeout=30)
        assert [json.loads(line)["seq"] for line in followed.splitlines()] == [0, 1, 2]
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0
        assert json.loads(out.strip().splitlines()[-1]) == {
            "event": "stopped",
            "exit_codes": {"inference": 0, "registration": 0, "map": 0},
        }
        logs = [json.loads(line) for line in (tmp_path / "registration.log").read_text().splitlines()]
        assert {"started", "shutdown requested", "stopped"} <= {e["event"] for e in logs}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
