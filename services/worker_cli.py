"""A worker's command line: `python -m occvo_services.<role>_worker [--config deploy/x.json5] [--connect ...] ...`."""

from __future__ import annotations

import sys
import threading
import traceback
from collections.abc import Callable

from occvo_core.errors import ConfigError
from occvo_services.os_tuning import few_malloc_arenas, large_blocks_from_mmap, short_gil_turns
from occvo_services.runtime import Worker
from occvo_services.sessions import NoRouterError
from occvo_services.store.url import SECRET_WAYS, redact, refuse_password, resolve
from occvo_services.worker_config import DEFAULT_ENDPOINT, WorkerConfig


def worker_main(
    worker_cls: type[Worker], argv: list[str] | None = None, extra_args: Callable | None = None, prog: str | None = None
) -> int:
    """`python -m occvo_services.<role>_worker [--config deploy/x.json5] [--connect ...] ...`"""
    import argparse

    p = argparse.ArgumentParser(prog=prog or f"python -m {_module_name(worker_cls)}", description=worker_cls.__doc__)
    p.add_argument("--config", help="worker json5 config (deploy/*.json5)")
    p.add_argument("--connect", help=f"router endpoint (default {DEFAULT_ENDPOINT})")
    p.add_argument("--worker-id")
    p.add_argument("--policy", choices=["lossless", "latest"])
    p.add_argument("--queue-size", type=int)
    p.add_argument("--max-message-bytes", type=int)
    p.add_argument("--log-level")
    p.add_argument("--router-wait-s", type=float, help="how long to wait at start for a router not up yet (default 60)")
    p.add_argument("--max-rss-mb", type=int, help="memory cap: idle streams evicted near it, new streams refused")
    p.add_argument(
        "--client-identity", choices=["session", "user"], help="who a client is: its Zenoh session, or the ACL user"
    )
    p.add_argument(
        "--store-url",
        help="the store: a SQLite file (path or sqlite:///path) or postgresql://user@host/db, without a password ("
        + SECRET_WAYS
        + ")",
    )
    p.add_argument("--store-url-file", help="a file readable by its owner only holding the store URL")
    if extra_args:
        extra_args(p)
    args = vars(p.parse_args(argv))
    _redacted_tracebacks()
    try:
        _store_url(args)
    except ConfigError as exc:  # one line and exit 2, before anything connects
        print(f"{p.prog}: {exc}", file=sys.stderr)
        return 2
    config = WorkerConfig.load(args.pop("config"), **args)
    large_blocks_from_mmap()
    few_malloc_arenas()
    short_gil_turns()
    try:
        return worker_cls(config).run_forever()
    except NoRouterError as exc:  # none came up within router_wait_s, or it refused the worker: one line
        print(f"{p.prog}: {exc}", file=sys.stderr)
        return 1


def _module_name(worker_cls: type[Worker]) -> str:
    """The module `python -m` ran: a worker class defined there is in __main__, whose spec keeps the name."""
    name = worker_cls.__module__
    spec = getattr(sys.modules.get(name), "__spec__", None) if name == "__main__" else None
    return spec.name if spec is not None else name


def _store_url(args: dict) -> None:
    """The store: --store-url / --store-path (a password there is refused: ps shows it), else --store-url-file,
    else OCCVO_STORE_URL in the environment (how `occvo serve` hands it over), else the config file's store_url."""
    url_file = args.pop("store_url_file")
    given = [refuse_password(args.get(k), "--" + k.replace("_", "-")) for k in ("store_url", "store_path")]
    if any(given):
        if url_file:
            raise ConfigError("give --store-url or --store-url-file, not both")
        return
    url = resolve(None, url_file)
    if url:  # both names: a config file giving store_path then names the same store, not a second one
        args["store_url"] = args["store_path"] = url


def _redacted_tracebacks() -> None:
    """An uncaught error's traceback (a driver may quote the store URL it was given) without the password."""

    def show(exc_type, exc, tb) -> None:
        sys.stderr.write(redact("".join(traceback.format_exception(exc_type, exc, tb))))

    sys.excepthook = show
    threading.excepthook = lambda a: show(a.exc_type, a.exc_value, a.exc_traceback)
