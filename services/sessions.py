"""Zenoh sessions for workers, routers and clients: loopback-friendly configs, the transport's message limit, the
router's endpoint from its config file."""

from __future__ import annotations

import json
import os
import re
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from occvo_core.errors import ConfigError
from occvo_schemas.codec import DEFAULT_MAX_BYTES
from occvo_services.worker_config import DEFAULT_ENDPOINT


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


ZENOH_CONFIG_ENV = "OCCVO_ZENOH_CONFIG"  # a zenoh json5 for client sessions: TLS certificates, credentials (deploy/)
CLIENT_RETRY = "{period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2}"
# Zenoh reassembles a fragmented message up to this many bytes and drops it beyond (its default, 1 GiB, let a huge
# put cost the router and a worker its size in memory before the codec's check). The codec's limit, so every message that reaches
# a worker's decode is within it; the registration worker splits bigger map updates (deploy/*.json5 set it too)
TRANSPORT_MAX_BYTES = DEFAULT_MAX_BYTES
_ZENOH_DEFAULT_MAX = 1 << 30


def limit_messages(c: zenoh.Config, max_bytes: int = TRANSPORT_MAX_BYTES) -> zenoh.Config:
    """Set the transport's largest reassembled message, unless the config file set its own; turn shared memory off.

    With zenoh's shared memory on (its default), every local client that sends more than 3 kB allocates a 16 MiB
    pool, and each process its messages reach (the router, the workers) maps that pool for as long as the client
    lives: the inference worker grew by a pool for each flooding client, given back only when it left. Off, the router
    and workers get their own copy of a message over the socket (a frame's copy costs well under a millisecond)."""
    if json.loads(c.get_json("transport/link/rx/max_message_size")) == _ZENOH_DEFAULT_MAX:
        c.insert_json5("transport/link/rx/max_message_size", str(max_bytes))
    c.insert_json5("transport/shared_memory/enabled", "false")
    return c


def zenoh_config(
    mode: str = "client", connect: str | None = None, listen: str | None = None, base: str | Path | None = None
) -> zenoh.Config:
    """Loopback-friendly config: no multicast scouting, explicit endpoints only. Client sessions start from
    `base` (default: the file named by $OCCVO_ZENOH_CONFIG) and retry a lost router every 0.5 s at most, so
    workers and clients reconnect within half a second of a router restart (zenoh's default waits up to 4 s)."""
    base = base or (os.environ.get(ZENOH_CONFIG_ENV) if mode == "client" else None)
    try:
        c = zenoh.Config.from_file(str(base)) if base else zenoh.Config()
    except Exception as exc:  # noqa: BLE001 - zenoh names the key, we name the file
        raise ConfigError(f"zenoh config {base}: {zenoh_reason(exc)}") from None
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    if connect:
        c.insert_json5("connect/endpoints", json.dumps([connect]))
    if listen:
        c.insert_json5("listen/endpoints", json.dumps([listen]))
    if mode == "client" and json.loads(c.get_json("connect/retry")) is None:
        c.insert_json5("connect/retry", CLIENT_RETRY)
    return limit_messages(c)


class NoRouterError(ConnectionError):
    """No Zenoh router answers at the endpoint (the message is the line for the user)."""


def zenoh_reason(exc: BaseException) -> str:
    """Zenoh's message for a user: one line, without the Rust source location or the error's struct around it."""
    text = " ".join(str(exc).split())
    quoted = re.search(r'msg: "(.*?)", location', text)  # Json5Err(Message { msg: "...", location: ... })
    text = quoted.group(1) if quoted else text
    parse = re.match(r"--> (\d+):(\d+) .*?= (.*)", text)  # a json5 parse error drawn as a source excerpt
    text = f"line {parse.group(1)}, column {parse.group(2)}: {parse.group(3)}" if parse else text
    return re.sub(r"\s*at /\S+\.rs:\d+\.?", "", text).strip(" .")


def open_session(
    connect: str = DEFAULT_ENDPOINT, base: str | Path | None = None, pick_up: bool = True
) -> zenoh.Session:
    """A client session on the router at connect; a malformed endpoint is a ConfigError and no router answering a
    NoRouterError, each one line. The config: `base`, else $OCCVO_ZENOH_CONFIG, else (pick_up) the client login
    `occvo serve` made for this user (client_login)."""
    return open_login(connect, base, pick_up)[0]


ROUTER_RETRY_S = 0.5  # a worker's tries for a router that is not up yet (open_worker_session)


def open_worker_session(
    connect: str, wait_s: float, stop: threading.Event, waiting: Callable[[str], None]
) -> zenoh.Session | None:
    """A worker's session, in its role's login, never the user's. A router nothing answers for yet is waited for up
    to wait_s (`waiting` is told once why); one that answers and refuses the session fails at once. None: `stop` was
    set while waiting."""
    deadline = time.monotonic() + wait_s
    told = False
    while True:
        try:
            return open_session(connect, pick_up=False)
        except NoRouterError as exc:
            if _answers(connect) or time.monotonic() >= deadline:
                raise
            if not told:
                waiting(str(exc))
                told = True
        if stop.wait(ROUTER_RETRY_S):
            return None


def client_login(base: str | Path | None = None, pick_up: bool = True) -> tuple[str | None, bool]:
    """The client config a session starts from and whether it was picked up by itself: `base`, $OCCVO_ZENOH_CONFIG,
    or this user's login file (services/logins.py) when there is one."""
    from occvo_services import logins

    given = base or os.environ.get(ZENOH_CONFIG_ENV)
    if given or not pick_up:
        return (str(given) if given else None), False
    own = logins.own_client_config()
    return (str(own) if own else None), own is not None


def open_login(
    connect: str = DEFAULT_ENDPOINT, base: str | Path | None = None, pick_up: bool = True
) -> tuple[zenoh.Session, str | None]:
    """open_session and the login it logged in as (None: no login). A login picked up by itself that the router
    refuses (a router without authentication, `occvo serve --anonymous`) is dropped: the session opens without."""
    from occvo_services.logins import login_of

    base, picked = client_login(base, pick_up)
    try:
        return _open(connect, base), login_of(base)
    except NoRouterError:
        if not picked or _answers(connect) is False:
            raise
    try:
        return _open(connect, None), None
    except NoRouterError:
        raise NoRouterError(
            f"the router at {connect} refused the login of {base} and a session without one (is it the router of "
            "the `occvo serve` that wrote it?)"
        ) from None


def _open(connect: str, base: str | None) -> zenoh.Session:
    try:
        config = zenoh_config("client", connect=connect, base=base)
    except zenoh.ZError as exc:
        raise ConfigError(f"{connect} is not a router endpoint: {zenoh_reason(exc)}") from None
    try:
        return zenoh.open(config)
    except zenoh.ZError:
        raise NoRouterError(_why_not(connect, base)) from None


def _why_not(connect: str, base: str | None) -> str:
    """Why no session opened, for the user: nothing listens, or a router there refused this session."""
    answers = _answers(connect)
    if answers and base:
        return f"the router at {connect} refused the session of {base}: check its certificates or credentials"
    if answers:
        return (
            f"the router at {connect} refused a session without a login: `occvo serve` makes one for the user who "
            "started it; another user or host gets one from `occvo logins add NAME` (OCCVO_ZENOH_CONFIG)"
        )
    maybe = f" (or it refused the session of {base}: check its certificates or credentials)" if base else ""
    return f"no router at {connect}{maybe if answers is None else ''}: start `occvo serve` or pass --connect"


def _answers(connect: str) -> bool | None:
    """Whether something accepts TCP connections at a tcp/ or tls/ endpoint (None: another kind of endpoint)."""
    proto, _, addr = connect.partition("/")
    host, _, port = addr.split("#")[0].rpartition(":")
    if proto not in ("tcp", "tls") or not port.isdigit():
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
            return True
    except OSError:
        return False


def open_router(listen: str | None = None, config_path: str | Path | None = None) -> zenoh.Session:
    """An in-process Zenoh router, from a json5 config file (deploy/router.json5) or a listen endpoint."""
    if config_path is not None:
        c = zenoh.Config.from_file(str(config_path))
        if listen:
            c.insert_json5("listen/endpoints", json.dumps([listen]))
        return zenoh.open(limit_messages(c))
    return zenoh.open(zenoh_config("router", listen=listen or DEFAULT_ENDPOINT))


def router_endpoint(config_path: str | Path) -> str:
    """The first listen endpoint of a router json5 config, for workers and clients to connect to."""
    import json5

    try:
        eps = json5.loads(Path(config_path).read_text())["listen"]["endpoints"]
        return eps[0]
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(f"{config_path}: no listen/endpoints[0] ({exc})") from None
