"""`occvo up`: the supervisor starts a router and the three workers (real processes, free loopback port), restarts a
worker killed with SIGKILL (new pid, alive again, its replay still gives the offline poses) with the configured
backoff, and stops everything cleanly on SIGTERM (workers first, then the router, every exit code 0)."""

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

from occvo_core.errors import ConfigError
from occvo_services.client import OccVOClient
from occvo_services.local import WORKERS, wait_alive
from occvo_services.sessions import free_port, open_session
from occvo_services.supervisor import Backoff, RestartSpec, UpConfig

REPO = Path(__file__).resolve().parents[2]
warnings.filterwarnings("ignore", category=RuntimeWarning)


def test_backoff_doubles_to_the_cap_and_resets_after_a_long_run():
    b = Backoff(RestartSpec(backoff_initial_s=0.5, backoff_max_s=30, reset_after_s=60))
    assert [b.next(uptime_s=1.0) for _ in range(9)] == [0.5, 1, 2, 4, 8, 16, 30, 30, 30]
    assert b.next(uptime_s=60.0) == 0.5 and b.next(uptime_s=0.1) == 1


def test_up_config_resolves_paths_and_names_bad_files(tmp_path):
    cfg = UpConfig.load(REPO / "deploy/occvo.json5")
    assert {w.role for w in cfg.workers} == set(WORKERS)
    assert all(Path(w.config).is_file() for w in cfg.workers) and cfg.endpoint() == "tcp/127.0.0.1:7447"
    bad = tmp_path / "up.json5"
    bad.write_text('{workers: [{role: "map", config: "nowhere.json5"}]}')
    with pytest.raises(ConfigError, match="nowhere.json5 not found"):
        UpConfig.load(bad)
    bad.write_text('{workers: [{role: "mapper"}]}')
    with pytest.raises(ConfigError, match="mapper"):
        UpConfig.load(bad)


def test_registration_replicas_are_shards(tmp_path):
    from occvo_services.supervisor import Supervisor

    up = tmp_path / "up.json5"
    up.write_text('{workers: [{role: "registration", count: 3}, {role: "map", count: 2}]}')
    sup = Supervisor(UpConfig.load(up))
    shards = {
        c.name: c.cmd[c.cmd.index("--shard") + 1 : c.cmd.index("--shard") + 4]
        for c in sup.workers
        if "--shard" in c.cmd
    }
    assert shards == {f"registration-{i}": [str(i), "--shards", "3"] for i in range(3)}  # map replicas are not shards


def _stats_pid(session, worker: str) -> int | None:
    from occvo_schemas import keys
    from occvo_schemas.codec import decode
    from occvo_schemas.models import WorkerHealth

    for r in session.get(keys.stats(worker), timeout=2.0):
        if r.ok:
            return decode(r.ok.payload.to_bytes(), WorkerHealth).pid
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_up_restarts_a_killed_worker_and_stops_cleanly(tmp_path):
    from occvo_core import OccVO
    from occvo_services.commands.replay import load_scene, replay

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    deploy = REPO / "deploy"
    (tmp_path / "up.json5").write_text(
        json.dumps(
            {
                "router": {"config": str(deploy / "router.json5"), "listen": ep},
                "workers": [
                    {"role": "inference", "config": str(deploy / "inference_worker.json5")},
                    {"role": "registration", "config": str(deploy / "registration_worker.json5")},
                    {"role": "map", "config": str(deploy / "map_service.json5")},
                ],
                "restart": {"backoff_initial_s": 0.5, "backoff_max_s": 4, "reset_after_s": 60},
                "stop_timeout_s": 30,
                "log_dir": str(tmp_path / "logs"),
            }
        )
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    err = open(tmp_path / "up.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "up", "--json", "--config", str(tmp_path / "up.json5")],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
    )
    pids: dict = {}
    try:
        scene = load_scene("synthetic:3", frames=4)  # the offline poses, while the service starts
        want = OccVO()
        want.reset()
        for i in range(4):
            want.step(scene[i])
        said = []  # stdout: listening, each worker as it comes up, then ready

        def read_until_ready():
            for line in proc.stdout:
                said.append(json.loads(line))
                if said[-1]["event"] == "ready":
                    return

        reader = threading.Thread(target=read_until_ready, daemon=True)
        reader.start()
        reader.join(600)  # a fresh install compiles the registration kernels first
        assert said and said[-1]["event"] == "ready", f"no ready line; log: {(tmp_path / 'up.log').read_text()}"
        assert said[0] == {"event": "listening", "endpoint": ep}
        ready = said[-1]
        pids = ready["pids"]
        assert ready["endpoint"] == ep
        assert set(pids) == {"router", "inference-0", "registration-0", "map-0"}
        probe = open_session(ep)
        try:
            wait_alive(probe, WORKERS, timeout=60)
            old = pids["registration-0"]
            assert _stats_pid(probe, "registration-0") == old
            os.kill(old, signal.SIGKILL)
            t_kill = time.monotonic()
            deadline = t_kill + 30
            new = None
            while time.monotonic() < deadline:
                new = _stats_pid(probe, "registration-0")
                if new not in (None, old):
                    break
                time.sleep(0.2)
            assert new not in (None, old), "registration worker did not come back"
            pids["registration-0b"] = new
            print(
                f"\nregistration worker SIGKILLed (pid {old}); back as pid {new} after {time.monotonic() - t_kill:.1f} s"
            )
            wait_alive(probe, WORKERS, timeout=10)
        finally:
            probe.close()
        with OccVOClient(ep, "after-restart") as client:
            out = replay(client, scene, window=2, timeout=60)
            assert out["poses"] == 4 and not client.errors
            assert np.abs(out["trajectory"] - want.poses).max() <= 1e-9

        events = [json.loads(x) for x in (tmp_path / "up.log").read_text().splitlines() if x.startswith("{")]
        crash = [e for e in events if e["event"] == "crashed"]
        assert len(crash) == 1 and crash[0]["name"] == "registration-0" and crash[0]["code"] == -signal.SIGKILL
        assert crash[0]["restart_in_s"] == 0.5 and crash[0]["how"] == "signal SIGKILL"
        restarted = [
            e for e in events if e["event"] == "started" and e["name"] == "registration-0" and e["restarts"] == 1
        ]
        assert len(restarted) == 1 and restarted[0]["pid"] == new
        gap = restarted[0]["ts"] - crash[0]["ts"]
        print(f"crash noticed -> restarted after {gap:.2f} s (backoff 0.5 s)")
        assert 0.5 <= gap < 2.0

        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0
        assert json.loads(rest.strip().splitlines()[-1]) == {"event": "stopped", "code": 0}
        events = [json.loads(x) for x in (tmp_path / "up.log").read_text().splitlines() if x.startswith("{")]
        stopped = next(e for e in events if e["event"] == "stopped" and e["logger"] == "occvo.up")
        assert stopped["exit_codes"] == {"inference-0": 0, "registration-0": 0, "map-0": 0, "router": 0}
        # workers stopped before the router: the router's log ends after every worker's
        logs = {
            n: [json.loads(x) for x in (tmp_path / "logs" / f"{n}.log").read_text().splitlines() if x.startswith("{")]
            for n in ("router", "inference-0", "registration-0", "map-0")
        }
        assert logs["router"][-1]["event"] == "router stopped"
        assert all(
            logs[n][-1]["event"] == "stopped" and logs[n][-1]["ts"] < logs["router"][-1]["ts"]
            for n in ("inference-0", "registration-0", "map-0")
        )
        assert not [p for p in pids.values() if p and _alive(p)]
    finally:
        if proc.poll() is None:
            proc.kill()  # its children get SIGTERM from the kernel (PR_SET_PDEATHSIG)
            proc.wait()
        for p in pids.values():
            if p and _alive(p):
                os.kill(p, signal.SIGKILL)
        err.close()
