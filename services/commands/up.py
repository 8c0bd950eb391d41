"""occvo up: the router and workers of a json5 file (deploy/occvo.json5), restarted when they crash; Ctrl-C stops all."""

from __future__ import annotations

from occvo_services import defaults
from occvo_services.commands._common import (
    WARM_UP_NOTE,
    ReadinessWatch,
    add_identity_flags,
    add_json,
    check_listen_secure,
    emit,
    listen_endpoints,
    progress,
    secure_default,
)
from occvo_services.store.factory import check_store


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("up", help="run and supervise the router and workers named in a json5 file")
    p.add_argument(
        "--config",
        default=None,
        help="deployment json5 (default: the built-in one; deploy/occvo.json5 is the deployment copy)",
    )
    p.add_argument("--listen", help="replace the router's listen endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--log-dir", help="each child's log to <dir>/<name>.log (default: stderr)")
    add_json(p, "the endpoint and events (listening, worker ready, ready, stopped)", lines=True)
    p.add_argument(
        "--quiet", action="store_true", help="no progress lines and only warnings of the supervisor's log on stderr"
    )
    add_identity_flags(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_services.ros2.config import Ros2NodeConfig
    from occvo_services.runtime import structured_logger
    from occvo_services.supervisor import Supervisor, UpConfig
    from occvo_services.worker_config import WorkerConfig

    config = UpConfig.load(args.config or defaults.path("occvo.json5"))
    for w in config.workers:  # one line and exit 2 for a bad worker config, not a worker crash-looping
        if w.role == "ros2":
            Ros2NodeConfig.load(w.config)  # the node's settings (docs/ros2.md)
        elif w.config:
            WorkerConfig.load(w.config).check_served(w.config)
    for url in sorted({u for w in config.workers if w.role in ("registration", "map") and (u := _worker_store(w))}):
        check_store(url, "a worker's store")  # once, before any worker starts
    if args.listen:
        config.router.listen, config.router.connect = args.listen, None
    if args.log_dir:
        config.log_dir = args.log_dir
    args.anonymous = args.anonymous or config.anonymous
    login = secure_default(args, config, given_router=config.router.config is not None)
    if config.router.enabled:
        router_file = config.router.config or str(defaults.path("router.json5"))
        listen = [config.router.listen] if config.router.listen else listen_endpoints(router_file)
        check_listen_secure(router_file, listen, args.insecure)
    sup = Supervisor(config, structured_logger("occvo.up", "WARNING") if args.quiet else None)
    sup.reload = args.logins_watch
    roles = tuple(dict.fromkeys(w.role for w in config.workers if w.role != "ros2"))  # the node has no token
    watch, ready = None, set()

    def worker_ready(role: str, seconds: float) -> None:
        if role == "warm-up":
            progress(args, "registration worker: warming up its kernels")
            return
        if args.json:
            emit(args, {"event": "worker ready", "role": role, "seconds": seconds}, "")
        progress(args, f"{role} worker ready after {seconds} s")
        ready.add(role)
        if ready == set(roles):  # the line a script waits for, as serve's
            pids = sup.pids()
            emit(
                args,
                {"event": "ready", "endpoint": sup.endpoint, "pids": pids},
                f"ready: {', '.join(f'{r} (pid {pid})' for r, pid in pids.items())}; Ctrl-C stops",
            )

    def started(s: Supervisor) -> None:
        nonlocal watch
        emit(args, {"event": "listening", "endpoint": s.endpoint}, f"listening on {s.endpoint}")
        if "registration" in roles:
            progress(args, f"workers started: {', '.join(roles)}; the registration worker {WARM_UP_NOTE}")
        watch = ReadinessWatch(s.endpoint, worker_ready, roles, login=login).start()

    try:
        code = sup.run(started)
    finally:
        if watch is not None:
            watch.stop()
    emit(args, {"event": "stopped", "code": code}, f"stopped (exit code {code})")
    return code


def _worker_store(w) -> str | None:
    """The store a worker will open, found as it finds it (services/worker_cli.py: its flags, then its environment,
    then its config file); a password in its args is refused, as on any command line."""
    import argparse
    import os

    from occvo_services.store.url import refuse_password, resolve
    from occvo_services.worker_config import WorkerConfig

    p = argparse.ArgumentParser(add_help=False)
    for flag in ("--store-url", "--store-path", "--store-url-file"):
        p.add_argument(flag)
    known, _ = p.parse_known_args(w.args)
    for flag, url in (("--store-url", known.store_url), ("--store-path", known.store_path)):
        refuse_password(url, f"{w.role} worker args: {flag}")
    url = known.store_url or known.store_path or resolve(None, known.store_url_file, env={**os.environ, **w.env})
    return WorkerConfig.load(w.config, store_url=url, store_path=url).store_url
