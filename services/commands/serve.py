"""occvo serve: a Zenoh router and the three workers on this machine, in one command; Ctrl-C stops them cleanly."""

from __future__ import annotations

import json
import signal
import threading

from occvo_core.errors import ConfigError
from services.commands._common import DEPLOY, endpoint
from services.local import LocalService


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("serve", help="start a router and the inference, registration and map workers")
    p.add_argument("--router-config", default=str(DEPLOY / "router.json5"), help="router json5 (listen endpoints)")
    p.add_argument("--connect", help="override the router listen endpoint, e.g. tcp/127.0.0.1:7447")
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


def run(args) -> int:
    if args.registration_workers < 1:
        raise ConfigError(f"--registration-workers must be at least 1, not {args.registration_workers}")
    ep = endpoint(args)
    store = ["--store-path", args.store_path] if args.store_path else []
    service = LocalService(
        endpoint=ep, router_config=args.router_config if not args.connect else None, log_dir=args.log_dir,
        registration_shards=args.registration_workers,
        common_args=["--policy", args.policy, "--queue-size", str(args.queue_size)],
        worker_args={"inference": ["--config", str(DEPLOY / "inference_worker.json5"), "--source", args.source, "--device", args.device,
                                   *(["--checkpoint", args.checkpoint] if args.checkpoint else [])],
                     "registration": ["--config", str(DEPLOY / "registration_worker.json5"), *store],
                     "map": ["--config", str(DEPLOY / "map_service.json5"), *store]})
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    service.start()
    print(json.dumps({"event": "ready", "endpoint": ep, "workers": {r: p.pid for r, p in service.procs.items()}}), flush=True)
    try:
        while not stop.wait(0.5):
            dead = {r: p.returncode for r, p in service.procs.items() if p.poll() is not None}
            if dead:
                print(json.dumps({"event": "worker exited", "codes": dead}), flush=True)
                break
    finally:
        codes = service.stop()
        print(json.dumps({"event": "stopped", "exit_codes": codes}), flush=True)
    return 0 if all(c == 0 for c in codes.values()) else 1
