"""occvo serve: a Zenoh router and the three workers on this machine, in one command, restarted when one crashes
(services/supervisor.py, as `occvo up`); Ctrl-C stops them cleanly."""

from __future__ import annotations

import json
import signal
import time

from occvo_core.errors import ConfigError
from services.commands._common import DEPLOY, check_listen_secure, endpoint


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("serve", help="start a router and the inference, registration and map workers")
    p.add_argument("--router-config", default=str(DEPLOY / "router.json5"), help="router json5 (listen endpoints)")
    p.add_argument("--connect", help="override the router listen endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--insecure", action="store_true", help="allow a non-loopback listen endpoint without authentication")
    p.add_argument("--source", choices=["replay", "model"], default="replay", help="inference source")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    p.add_argument("--checkpoint", help="TPV-Former checkpoint for --source model (occvo train-occ)")
    p.add_argument("--store-path", help="SQLite file for the trajectories and the map; a restart resumes from it")
    p.add_argument("--policy", choices=["lossless", "latest"], default="lossless")
    p.add_argument("--queue-size", type=int, default=4)
    p.add_argument("--registration-workers", type=int, default=1,
                   help="registration workers sharing the streams (shards by stream id, one core each)")
    p.add_argument("--log-dir", help="write each worker's JSON log lines to <dir>/<role>.log (default: stderr)")
    p.set_defaults(func=run)


def _wait_alive(sup, timeout: float = 180.0) -> None:
    """Until every worker's liveliness token is up (a fresh install compiles kernels first), restarting crashes."""
    from schemas import keys
    from services.runtime import open_session

    roles = {"inference", "registration", "map"}
    probe = open_session(sup.endpoint)
    try:
        deadline = time.monotonic() + timeout
        while not sup.stopping.is_set():
            sup.poll()
            alive = {str(r.ok.key_expr).split("/")[2] for r in probe.liveliness().get(keys.alive(), timeout=1.0) if r.ok}
            shards = [r for r in probe.liveliness().get(keys.registration_shard(), timeout=1.0) if r.ok]
            if roles <= alive and len(shards) >= sum(c.role == "registration" for c in sup.workers):
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"workers {sorted(roles - alive)} not alive after {timeout} s")
            time.sleep(0.1)
    finally:
        probe.close()


def run(args) -> int:
    from services.supervisor import RouterSpec, Supervisor, UpConfig, WorkerSpec

    if args.registration_workers < 1:
        raise ConfigError(f"--registration-workers must be at least 1, not {args.registration_workers}")
    ep = endpoint(args)
    check_listen_secure(args.router_config, [ep], args.insecure)
    store = ["--store-path", args.store_path] if args.store_path else []
    common = ["--policy", args.policy, "--queue-size", str(args.queue_size)]
    config = UpConfig(
        router=RouterSpec(config=args.router_config, listen=ep if args.connect else None), log_dir=args.log_dir,
        workers=[WorkerSpec(role="inference", config=str(DEPLOY / "inference_worker.json5"),
                            args=[*common, "--source", args.source, "--device", args.device,
                                  *(["--checkpoint", args.checkpoint] if args.checkpoint else [])]),
                 WorkerSpec(role="registration", config=str(DEPLOY / "registration_worker.json5"), args=[*common, *store],
                            count=args.registration_workers),
                 WorkerSpec(role="map", config=str(DEPLOY / "map_service.json5"), args=[*common, *store])])
    sup = Supervisor(config, role_names=True)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: sup.stopping.set())
    try:
        sup.start()
        _wait_alive(sup)
        if not sup.stopping.is_set():
            print(json.dumps({"event": "ready", "endpoint": sup.endpoint,
                              "workers": {c.name: c.proc.pid for c in sup.workers}}), flush=True)
        while not sup.stopping.wait(0.1):
            sup.poll()  # a crashed worker is started again after its backoff
    finally:
        codes = sup.stop()
        worker_codes = {c.name: codes.get(c.name) for c in sup.workers}
        print(json.dumps({"event": "stopped", "exit_codes": worker_codes}), flush=True)
    # -SIGTERM: a worker stopped while still importing, before it had anything in hand
    return 0 if all(c in (0, None, -signal.SIGTERM) for c in codes.values()) else 1
