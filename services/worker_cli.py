"""A worker's command line: `python -m occvo_services.<role>_worker [--config deploy/x.json5] [--connect ...] ...`."""

from __future__ import annotations

from collections.abc import Callable

from occvo_services.os_tuning import few_malloc_arenas, large_blocks_from_mmap
from occvo_services.runtime import Worker
from occvo_services.worker_config import DEFAULT_ENDPOINT, WorkerConfig


def worker_main(
    worker_cls: type[Worker], argv: list[str] | None = None, extra_args: Callable | None = None, prog: str | None = None
) -> int:
    """`python -m occvo_services.<role>_worker [--config deploy/x.json5] [--connect ...] ...`"""
    import argparse

    p = argparse.ArgumentParser(prog=prog or f"python -m {worker_cls.__module__}", description=worker_cls.__doc__)
    p.add_argument("--config", help="worker json5 config (deploy/*.json5)")
    p.add_argument("--connect", help=f"router endpoint (default {DEFAULT_ENDPOINT})")
    p.add_argument("--worker-id")
    p.add_argument("--policy", choices=["lossless", "latest"])
    p.add_argument("--queue-size", type=int)
    p.add_argument("--max-message-bytes", type=int)
    p.add_argument("--log-level")
    p.add_argument("--max-rss-mb", type=int, help="memory cap: idle streams evicted near it, new streams refused")
    p.add_argument(
        "--client-identity", choices=["session", "user"], help="who a client is: its Zenoh session, or the ACL user"
    )
    p.add_argument("--store-url", help="the store: a SQLite file (path or sqlite:///path) or postgresql://...")
    if extra_args:
        extra_args(p)
    args = vars(p.parse_args(argv))
    config = WorkerConfig.load(args.pop("config"), **args)
    large_blocks_from_mmap()
    few_malloc_arenas()
    return worker_cls(config).run_forever()
