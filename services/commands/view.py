"""occvo view: follow a running service's stream (poses, occupancy, map updates over Zenoh) in a rerun view, into an
MCAP file for Foxglove, or live to Foxglove over its WebSocket protocol."""

from __future__ import annotations

import json
import signal
import threading
import time

from occvo_cli.paths import out_file
from occvo_services.commands._common import add_connection, endpoint
from occvo_services.stop_signals import set_on_signal


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "view",
        help="follow a stream of the running service in a rerun viewer (pip install 'occvo[view]') or Foxglove "
        "(--mcap, --foxglove; pip install 'occvo[foxglove]')",
    )
    add_connection(p)
    p.add_argument(
        "--rerun", type=out_file(make_parents=True), metavar="FILE.rrd", help="save what arrives as a rerun recording"
    )
    p.add_argument(
        "--web-port",
        type=int,
        help="serve the web viewer on this port (the data on the next one) instead of spawning the native viewer",
    )
    p.add_argument(
        "--mcap",
        type=out_file(make_parents=True),
        metavar="FILE.mcap",
        help="write what arrives to an MCAP file in Foxglove's schemas",
    )
    p.add_argument(
        "--foxglove",
        type=int,
        nargs="?",
        const=8765,
        metavar="PORT",
        help="serve what arrives live to Foxglove over its WebSocket protocol on --bind's address, port PORT "
        "(default 8765)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --rerun or --mcap file that occvo did not write (default: refused; docs/cli.md)",
    )
    p.add_argument(
        "--bind",
        default="127.0.0.1",
        metavar="HOST",
        help="the address the viewers this command serves listen on (--web-port and its data, --foxglove): "
        "127.0.0.1 (default, this machine only), 0.0.0.0 for every interface",
    )
    p.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)")
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_core.overwrite import check_replaceable
    from occvo_core.viz.views import Views
    from occvo_services.follow import StreamFollower
    from occvo_services.logins import own_stream
    from occvo_services.sessions import open_login

    foxglove = args.mcap is not None or args.foxglove is not None
    check_replaceable(args.rerun, "rrd", "--rerun", args.force)
    check_replaceable(args.mcap, "mcap", "--mcap", args.force)
    session, login = open_login(endpoint(args))  # first: no router, no viewer and no recording
    args.stream = own_stream(args.stream, login)  # a login follows its own streams, under its prefix
    views = []
    try:
        if args.rerun or args.web_port or not foxglove:
            views.append(_rerun_view(args))
        if foxglove:
            views.append(_foxglove_view(args))
    except BaseException:
        Views(views).abandon()
        session.close()
        raise
    view = Views(views)
    follower = StreamFollower(session, args.stream, view)
    stop = threading.Event()
    set_on_signal(stop, (signal.SIGTERM,))
    ended = False
    try:
        host = "127.0.0.1" if args.bind in ("0.0.0.0", "::") else args.bind
        if args.web_port:
            print(
                f"web viewer: http://{host}:{args.web_port}/?url=rerun%2Bhttp%3A%2F%2F{host}%3A"
                f"{args.web_port + 1}%2Fproxy",
                flush=True,
            )
        if args.foxglove is not None:  # Foxglove: Open connection, Foxglove WebSocket, this URL
            print(f"foxglove: ws://{host}:{views[-1].port}", flush=True)
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


def _rerun_view(args):
    from occvo_core.errors import ConfigError

    try:
        from occvo_core.viz.rerun_log import RerunView
    except ModuleNotFoundError as exc:
        if exc.name != "rerun":
            raise
        raise ConfigError("occvo view needs rerun-sdk: pip install 'occvo[view]'") from None
    try:
        return RerunView.open(
            f"occvo-{args.stream}",
            spawn=not (args.rerun or args.web_port),
            save=args.rerun,
            web_port=args.web_port,
            bind=args.bind,
        )
    except RuntimeError as exc:  # e.g. the ports are taken
        raise ConfigError(f"--web-port {args.web_port}: {exc}") from None


def _foxglove_view(args):
    from occvo_core.errors import ConfigError

    try:
        from occvo_core.viz.foxglove_log import FoxgloveView
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in ("foxglove", "mcap"):
            raise
        raise ConfigError("--mcap and --foxglove need foxglove-sdk: pip install 'occvo[foxglove]'") from None
    try:
        return FoxgloveView(mcap=args.mcap, port=args.foxglove, host=args.bind)
    except RuntimeError as exc:  # e.g. the port is taken
        raise ConfigError(f"--foxglove {args.foxglove}: {exc}") from None
