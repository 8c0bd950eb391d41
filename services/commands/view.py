"""occvo view: follow a running service's stream (poses, occupancy, map updates over Zenoh) in a rerun view."""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

from occvo_services.commands._common import add_connection, endpoint


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="follow a stream of the running service in a rerun viewer (pip install 'occvo[view]')"
    )
    add_connection(p)
    p.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="save what arrives as a rerun recording")
    p.add_argument(
        "--web-port",
        type=int,
        help="serve the web viewer on this port (the data on the next one) instead of spawning the native viewer",
    )
    p.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)")
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_core.errors import ConfigError

    try:
        from occvo_core.viz.rerun_log import RerunView
        from occvo_services.follow import StreamFollower
    except ModuleNotFoundError as exc:
        if exc.name != "rerun":
            raise
        raise ConfigError("occvo view needs rerun-sdk: pip install 'occvo[view]'") from None
    from occvo_services.sessions import open_session

    session = open_session(endpoint(args))  # first: no router, no viewer and no recording
    try:
        view = RerunView.open(
            f"occvo-{args.stream}", spawn=not (args.rerun or args.web_port), save=args.rerun, web_port=args.web_port
        )
    except BaseException:
        session.close()
        raise
    follower = StreamFollower(session, args.stream, view)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    ended = False
    try:
        if args.web_port:
            print(
                f"web viewer: http://127.0.0.1:{args.web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A"
                f"{args.web_port + 1}%2Fproxy",
                flush=True,
            )
        deadline = time.monotonic() + args.seconds if args.seconds > 0 else None
        while not stop.wait(0.2):
            if deadline is not None and time.monotonic() > deadline:
                break
        ended = True
    except KeyboardInterrupt:  # Ctrl-C is how a viewer ends: close and print the counts
        ended = True
    finally:
        follower.close()
        session.close()
        view.close() if ended else view.abandon()  # a recording is kept only when it ended as asked
    print(json.dumps({"stream": args.stream, **follower.counts}))
    return 0
