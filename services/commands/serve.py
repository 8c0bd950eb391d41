"""occvo serve: a Zenoh router and the three workers on this machine, in one command, restarted when one crashes
(services/supervisor.py, as `occvo up`); Ctrl-C stops them cleanly."""

from __future__ import annotations

import signal
import time
from pathlib import Path

from occvo_core.errors import ConfigError
from occvo_services import defaults
from occvo_services.client import ServiceError
from occvo_services.commands._common import (
    WARM_UP_NOTE,
    ReadinessWatch,
    add_identity_flags,
    add_json,
    check_listen_secure,
    emit,
    endpoint,
    listen_endpoints,
    progress,
    secure_default,
)
from occvo_services.stop_signals import set_on_signal
from occvo_services.store.factory import check_store
from occvo_services.store.url import resolve as resolve_store_url


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("serve", help="start a router and the inference, registration and map workers")
    p.add_argument("--router-config", default=None, help="router json5 (listen endpoints; default: the built-in one)")
    p.add_argument("--listen", help="the router's listen endpoint instead of the config's, e.g. tcp/127.0.0.1:7447")
    p.add_argument(
        "--config-dir",
        help="a folder with inference_worker.json5, registration_worker.json5 and "
        "map_service.json5 overriding the built-in worker configs (e.g. deploy)",
    )
    add_identity_flags(p)
    p.add_argument("--source", choices=["replay", "model"], default="replay", help="inference source")
    p.add_argument(
        "--device",
        choices=["auto", "cpu", "cuda"],
        default="auto",
        help="where --source model runs the network (auto: cuda when there is one)",
    )
    p.add_argument("--checkpoint", help="TPV-Former checkpoint for --source model (occvo train-occ)")
    _store_flags(p)
    p.add_argument(
        "--policy",
        choices=["lossless", "latest"],
        default="lossless",
        help="a full queue: lossless blocks the sender, latest drops the oldest frame (default lossless)",
    )
    p.add_argument("--queue-size", type=int, default=4, help="frames each worker holds a stream before its policy acts")
    _registration_flags(p)
    p.add_argument(
        "--ros2", action="store_true", help="also join a ROS 2 graph as a node, rmw_zenoh's way (docs/ros2.md)"
    )
    p.add_argument("--ros2-config", metavar="FILE", help="the ROS 2 node's json5: domain, namespace, input, topics")
    p.add_argument("--log-dir", help="write each worker's JSON log lines to <dir>/<role>.log (default: stderr)")
    p.add_argument(
        "--start-timeout",
        type=float,
        default=300.0,
        help="seconds the workers may take to come up (a first start compiles the kernels)",
    )
    add_json(p, "the endpoint and events (listening, worker ready, ready, stopped)", lines=True)
    p.add_argument("--quiet", action="store_true", help="no progress lines and no worker logs on stderr")
    p.set_defaults(func=run)


def _store_flags(p) -> None:
    p.add_argument(
        "--store",
        "--store-path",
        dest="store",
        metavar="URL",
        help="the trajectories' and the map's store, a restart resumes from it: a SQLite file (path or sqlite:///path) "
        "or postgresql://user@host/db shared by the workers of many hosts; a password is refused here (default: "
        "$OCCVO_STORE_URL)",
    )
    p.add_argument(
        "--store-url-file",
        metavar="FILE",
        help="a file readable by its owner only holding the store URL, password and all (instead of --store)",
    )


def _registration_flags(p) -> None:
    p.add_argument(
        "--registration-workers",
        type=int,
        default=1,
        help="registration workers sharing the streams (one core each), as --placement says",
    )
    p.add_argument(
        "--placement",
        choices=["shards", "members"],
        default="shards",
        help="shards: by stream id; members: the live workers share the streams under leases in the store (needs "
        "--store; PostgreSQL for workers on many hosts)",
    )


def _worker_config(args, name: str) -> str:
    """The worker config's path, checked here (one line and exit 2 for a bad one, not a worker crash-looping)."""
    from occvo_services.worker_config import WorkerConfig

    if not args.config_dir:
        path = str(defaults.path(name))
    else:
        path = str(Path(args.config_dir).resolve() / name)  # the workers run in another folder
        if not Path(path).is_file():
            raise ConfigError(f"--config-dir {args.config_dir} has no {name}")
    WorkerConfig.load(path, policy=args.policy, queue_size=args.queue_size, store_url=args.store).check_served(path)
    return path


def _absolute(path: str | None) -> str | None:
    """A path given relative to the current folder, absolute (the workers run in another folder); URLs kept."""
    if path is None or "://" in path:
        return path
    return str(Path(path).resolve())


def _wait_alive(sup, timeout: float, login=None) -> None:
    """Until every worker's liveliness token is up (a fresh install compiles kernels first), restarting crashes."""
    from occvo_schemas import keys
    from occvo_services.sessions import NoRouterError, open_session

    roles = {"inference", "registration", "map"}
    try:
        probe = open_session(sup.endpoint, base=login, pick_up=False)
    except NoRouterError:
        router = sup.router.proc if sup.router is not None else None
        if router is None or router.poll() is None:
            raise
        raise ServiceError(
            f"the router could not listen on {sup.endpoint} (exit code {router.returncode}; is the port taken by "
            "another program?): give another --listen"
        ) from None
    try:
        deadline = time.monotonic() + timeout
        while not sup.stopping.is_set():
            sup.poll()
            alive = {
                str(r.ok.key_expr).split("/")[2] for r in probe.liveliness().get(keys.alive(), timeout=1.0) if r.ok
            }
            shards = [r for r in probe.liveliness().get(keys.registration_shard(), timeout=1.0) if r.ok]
            if roles <= alive and len(shards) >= sum(c.role == "registration" for c in sup.workers):
                return
            if time.monotonic() > deadline:
                raise ServiceError(f"workers {sorted(roles - alive)} not up after {timeout:.0f} s (see --log-dir)")
            time.sleep(0.1)
    finally:
        probe.close()


def _up_config(args, router_config: str):
    """The router and the three workers `occvo serve` supervises, from its flags."""
    from occvo_services.store.url import STORE_URL_ENV
    from occvo_services.supervisor import RouterSpec, UpConfig, WorkerSpec

    store = {STORE_URL_ENV: args.store} if args.store else {}  # the environment: argv is anyone's to read (ps)
    common = ["--policy", args.policy, "--queue-size", str(args.queue_size)]
    model = [
        "--source",
        args.source,
        "--device",
        args.device,
        *(["--checkpoint", args.checkpoint] if args.checkpoint else []),
    ]
    return UpConfig(
        router=RouterSpec(config=router_config, listen=args.listen),
        log_dir=args.log_dir,
        workers=[
            WorkerSpec(role="inference", config=_worker_config(args, "inference_worker.json5"), args=[*common, *model]),
            WorkerSpec(
                role="registration",
                config=_worker_config(args, "registration_worker.json5"),
                args=[*common, "--placement", args.placement],
                count=args.registration_workers,
                env=store,
            ),
            WorkerSpec(role="map", config=_worker_config(args, "map_service.json5"), args=common, env=store),
            *([WorkerSpec(role="ros2", config=_ros2_config(args))] if args.ros2 or args.ros2_config else []),
        ],
    )


def _ros2_config(args) -> str | None:
    """The ROS 2 node's settings, checked here (one line and exit 2, not a node crash-looping)."""
    if args.ros2_config is None:
        return None
    from occvo_services.ros2.config import Ros2NodeConfig

    path = _absolute(args.ros2_config)
    Ros2NodeConfig.load(path)
    return path


def run(args) -> int:
    from occvo_services.runtime import structured_logger
    from occvo_services.supervisor import Supervisor

    if args.registration_workers < 1:
        raise ConfigError(f"--registration-workers must be at least 1, not {args.registration_workers}")
    if args.queue_size < 1:
        raise ConfigError(f"--queue-size must be at least 1, not {args.queue_size}")
    args.store, args.checkpoint, args.log_dir = (
        _absolute(resolve_store_url(args.store, args.store_url_file)),
        _absolute(args.checkpoint),
        _absolute(args.log_dir),
    )
    if args.placement == "members" and not args.store:
        raise ConfigError("--placement members needs a store (--store): the workers hand streams over through it")
    if args.anonymous and args.router_config:
        raise ConfigError("--anonymous runs the built-in router without logins: give it or --router-config, not both")
    given_router = args.router_config is not None
    router_config = _absolute(args.router_config) or str(defaults.path("router.json5"))
    args.router_config = router_config
    if not Path(router_config).is_file():
        raise ConfigError(f"router config {router_config} not found")
    check_store(args.store)  # once, before any worker: one line and exit 2, not workers crash-looping
    ep = args.listen or endpoint(args)
    config = _up_config(args, router_config)  # the worker configs validated
    # the default: the router with logins and access control, the workers as their logins (services/acl.py)
    args.probe_login = secure_default(args, config, given_router)
    router_config = config.router.config
    check_listen_secure(router_config, [args.listen] if args.listen else listen_endpoints(router_config), args.insecure)
    if args.log_dir:
        Path(args.log_dir).mkdir(parents=True, exist_ok=True)
    sup = Supervisor(
        config, structured_logger("occvo.serve", "WARNING") if args.quiet else None, role_names=True, quiet=args.quiet
    )
    sup.reload = args.logins_watch
    set_on_signal(sup.stopping)
    emit(args, {"event": "listening", "endpoint": ep}, f"listening on {ep}")
    progress(args, f"starting the inference, registration and map workers; the registration worker {WARM_UP_NOTE}")
    return _supervise(args, sup, ep)


def _supervise(args, sup, ep: str) -> int:
    """Start the workers, say when they are ready, restart crashed ones until Ctrl-C; the exit code of the stop."""

    def ready(role: str, seconds: float) -> None:
        if role == "warm-up":
            progress(args, "registration worker: warming up its kernels")
            return
        if args.json:
            emit(args, {"event": "worker ready", "role": role, "seconds": seconds}, "")
        progress(args, f"{role} worker ready after {seconds} s")

    watch = ReadinessWatch(ep, ready, login=args.probe_login).start()
    try:
        sup.start()
        up = False
        try:
            _wait_alive(sup, args.start_timeout, args.probe_login)
            up = True
        finally:  # "ready" only for workers seen alive: not for one that never came up
            watch.stop(all_ready=up and not sup.stopping.is_set())
        if not sup.stopping.is_set():
            workers = {c.name: c.proc.pid for c in sup.workers}
            emit(
                args,
                {"event": "ready", "endpoint": ep, "workers": workers},
                f"ready: {', '.join(f'{r} (pid {pid})' for r, pid in workers.items())}; Ctrl-C stops",
            )
        while not sup.stopping.wait(0.1):
            sup.poll()  # a crashed worker is started again after its backoff
    finally:
        codes = sup.stop()
        worker_codes = {c.name: codes.get(c.name) for c in sup.workers}
        emit(
            args,
            {"event": "stopped", "exit_codes": worker_codes},
            f"stopped: {', '.join(f'{r} exit code {c}' for r, c in worker_codes.items())}",
        )
    # -SIGTERM: a worker stopped while still importing, before it had anything in hand
    return 0 if all(c in (0, None, -signal.SIGTERM) for c in codes.values()) else 1
