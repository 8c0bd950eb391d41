"""occvo serve: a Zenoh router and the three workers on this machine, in one command; Ctrl-C stops them cleanly."""

from __future__ import annotations

import signal
import threading
from pathlib import Path

from occvo_core.errors import ConfigError
from services import defaults
from services.commands._common import WARM_UP_NOTE, ReadinessWatch, add_json, emit, endpoint, progress
from services.local import LocalService


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("serve", help="start a router and the inference, registration and map workers")
    p.add_argument("--router-config", default=None, help="router json5 (listen endpoints; default: the built-in one)")
    p.add_argument("--listen", help="the router's listen endpoint instead of the config's, e.g. tcp/127.0.0.1:7447")
    p.add_argument(
        "--config-dir",
        help="a folder with inference_worker.json5, registration_worker.json5 and "
        "map_service.json5 overriding the built-in worker configs (e.g. deploy)",
    )
    p.add_argument("--source", choices=["replay", "model"], default="replay", help="inference source")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    p.add_argument("--checkpoint", help="TPV-Former checkpoint for --source model (occvo train-occ)")
    p.add_argument("--store-path", help="SQLite file for the trajectories and the map; a restart resumes from it")
    p.add_argument("--policy", choices=["lossless", "latest"], default="lossless")
    p.add_argument("--queue-size", type=int, default=4)
    p.add_argument(
        "--registration-workers",
        type=int,
        default=1,
        help="registration workers sharing the streams (shards by stream id, one core each)",
    )
    p.add_argument("--log-dir", help="write each worker's JSON log lines to <dir>/<role>.log (default: stderr)")
    p.add_argument(
        "--start-timeout",
        type=float,
        default=300.0,
        help="seconds the workers may take to come up (a first start compiles the kernels)",
    )
    add_json(p, "the endpoint and events (listening, worker ready, ready, stopped) as JSON lines")
    p.add_argument("--quiet", action="store_true", help="no progress lines and no worker logs on stderr")
    p.set_defaults(func=run)


def _worker_config(args, name: str) -> str:
    if not args.config_dir:
        return str(defaults.path(name))
    path = f"{args.config_dir}/{name}"
    if not Path(path).is_file():
        raise ConfigError(f"--config-dir {args.config_dir} has no {name}")
    return path


def run(args) -> int:
    if args.registration_workers < 1:
        raise ConfigError(f"--registration-workers must be at least 1, not {args.registration_workers}")
    if args.queue_size < 1:
        raise ConfigError(f"--queue-size must be at least 1, not {args.queue_size}")
    router_config = args.router_config or str(defaults.path("router.json5"))
    if args.log_dir:
        Path(args.log_dir).mkdir(parents=True, exist_ok=True)
    ep = args.listen or endpoint(args)
    store = ["--store-path", args.store_path] if args.store_path else []
    service = LocalService(
        endpoint=ep,
        router_config=router_config if not args.listen else None,
        log_dir=args.log_dir,
        quiet=args.quiet,
        registration_shards=args.registration_workers,
        common_args=["--policy", args.policy, "--queue-size", str(args.queue_size)],
        worker_args={
            "inference": [
                "--config",
                _worker_config(args, "inference_worker.json5"),
                "--source",
                args.source,
                "--device",
                args.device,
                *(["--checkpoint", args.checkpoint] if args.checkpoint else []),
            ],
            "registration": ["--config", _worker_config(args, "registration_worker.json5"), *store],
            "map": ["--config", _worker_config(args, "map_service.json5"), *store],
        },
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    emit(args, {"event": "listening", "endpoint": ep}, f"listening on {ep}")
    progress(args, f"starting the inference, registration and map workers; the registration worker {WARM_UP_NOTE}")

    def ready(role: str, seconds: float) -> None:
        if role == "warm-up":
            progress(args, "registration worker: warming up its kernels")
            return
        if args.json:
            emit(args, {"event": "worker ready", "role": role, "seconds": seconds}, "")
        progress(args, f"{role} worker ready after {seconds} s")

    watch = ReadinessWatch(ep, ready).start()
    started = False
    try:
        service.start(timeout=args.start_timeout)
        started = True
    finally:
        watch.stop(all_ready=started)
    emit(
        args,
        {"event": "ready", "endpoint": ep, "workers": {r: p.pid for r, p in service.procs.items()}},
        f"ready: {', '.join(f'{r} (pid {p.pid})' for r, p in service.procs.items())}; Ctrl-C stops",
    )
    try:
        while not stop.wait(0.5):
            dead = {r: p.returncode for r, p in service.procs.items() if p.poll() is not None}
            if dead:
                progress(args, f"workers exited: {dead}")
                break
    finally:
        codes = service.stop()
        emit(
            args,
            {"event": "stopped", "exit_codes": codes},
            f"stopped: {', '.join(f'{r} exit code {c}' for r, c in codes.items())}",
        )
    return 0 if all(c == 0 for c in codes.values()) else 1
