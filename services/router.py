"""A Zenoh router from a json5 file, until SIGTERM or SIGINT.

    python -m occvo_services.router --config deploy/router.json5 [--listen tcp/0.0.0.0:7447] [--connect tcp/other:7447]

`--listen` / `--connect` replace the file's endpoints (tests on free ports, one file for several hosts). Logs are
JSON lines on stderr; the first line after the router is up is {"event": "router ready", ...}.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
from pathlib import Path

import zenoh

from occvo_core.errors import ConfigError
from occvo_services import defaults
from occvo_services.runtime import log_event, structured_logger
from occvo_services.sessions import limit_messages
from occvo_services.stop_signals import set_on_signal

DEFAULT_CONFIG = defaults.path("router.json5")


def router_config(
    path: str | Path | None = None, listen: list[str] | None = None, connect: list[str] | None = None
) -> zenoh.Config:
    """The router's zenoh.Config: the json5 file (mode forced to router), endpoints replaced when given."""
    path = Path(path or DEFAULT_CONFIG)
    if not path.is_file():
        raise ConfigError(f"router config {path} not found")
    try:
        c = zenoh.Config.from_file(str(path))
    except Exception as exc:  # noqa: BLE001 - zenoh names the bad key; we name the file
        raise ConfigError(f"router config {path}: {exc}") from None
    c.insert_json5("mode", '"router"')
    if listen:
        c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return limit_messages(c)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m occvo_services.router", description=__doc__.split("\n")[0])
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="router json5 (default: the built-in one)")
    p.add_argument("--listen", action="append", help="listen endpoint, replaces the file's (repeatable)")
    p.add_argument("--connect", action="append", help="endpoint of another router to mesh with (repeatable)")
    p.add_argument("--log-level", default="INFO")
    args = p.parse_args(argv)
    log = structured_logger("occvo.router", args.log_level)
    stop = threading.Event()
    set_on_signal(stop)
    try:
        config = router_config(args.config, args.listen, args.connect)
        session = zenoh.open(config)
    except Exception as exc:  # noqa: BLE001 - one line naming the problem, no traceback
        log_event(log, "router failed", logging.ERROR, config=args.config, error=str(exc))
        return 2
    log_event(
        log,
        "router ready",
        zid=str(session.info.zid()),
        config=args.config,
        pid=os.getpid(),
        listen=json.loads(config.get_json("listen/endpoints")),
        connect=json.loads(config.get_json("connect/endpoints")),
    )
    while not stop.wait(0.2):  # short waits keep the main thread responsive to signals
        continue
    log_event(log, "router stopping", pid=os.getpid())
    session.close()
    log_event(log, "router stopped", pid=os.getpid())
    return 0


if __name__ == "__main__":
    sys.exit(main())
