"""What every service command shares: where the router is, which stream, --json/--quiet, one-line errors, and the
readiness of the workers as it comes."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

from occvo_core.errors import ConfigError
from occvo_schemas import keys
from occvo_services import defaults
from occvo_services.runtime import DEFAULT_ENDPOINT
from occvo_services.sessions import router_endpoint

ROLES = ("inference", "registration", "map")
WARM_UP_NOTE = "compiles its kernels on a first start, ~40 s on 2 cores; loads them from the cache after"


def stream_id(text: str) -> str:
    try:
        return keys.check_stream(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_connection(p, stream: bool = True) -> None:
    p.add_argument(
        "--connect", help=f"router endpoint (default: listen endpoint of --router-config, else {DEFAULT_ENDPOINT})"
    )
    p.add_argument("--router-config", default=None, help="router json5 config (default: the built-in one)")
    if stream:
        p.add_argument("--stream", type=stream_id, default="default", help="stream id (default: default)")
    p.add_argument(
        "--query-timeout", type=float, default=2.0, help="seconds a query waits for its answers (default: 2)"
    )


def add_json(p, what: str = "the result", lines: bool = False) -> None:
    p.add_argument("--json", action="store_true", help=f"{what} as JSON{' lines' if lines else ''} on stdout")


def endpoint(args) -> str:
    if getattr(args, "connect", None):
        return args.connect
    cfg = getattr(args, "router_config", None) or defaults.path("router.json5")
    if not Path(cfg).is_file():
        raise ConfigError(f"router config {cfg} not found: give an existing --router-config or --connect")
    return router_endpoint(cfg)


def client(args, **kw):
    """An OccVOClient on the command's router (no router answering: open_session's NoRouterError, one line)."""
    from occvo_services.client import OccVOClient

    timeout = getattr(args, "query_timeout", 2.0)
    if timeout <= 0:
        raise ConfigError(f"--query-timeout must be more than 0, got {timeout}")
    return OccVOClient(endpoint(args), stream=getattr(args, "stream", "default"), query_timeout=timeout, **kw)


def emit(args, record: dict, text: str) -> None:
    """One result on stdout: the record as JSON with --json, else the text."""
    print(json.dumps(record) if args.json else text, flush=True)


def progress(args, text: str) -> None:
    """A progress line on stderr, unless --quiet."""
    if not getattr(args, "quiet", False):
        print(f"occvo {args.command}: {text}", file=sys.stderr, flush=True)


class ReadinessWatch:
    """Reports each worker role as its liveliness token appears (the registration worker announces itself after its
    kernels' warm-up), from a thread with its own session, until stop()."""

    def __init__(self, ep: str, report, roles=ROLES, login=None):
        """login: the client config to watch with (the command's own; None: as any client)."""
        self.ep, self.report, self.roles, self.login = ep, report, roles, login
        self.t0 = time.monotonic()
        self.seen: set[str] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="occvo-readiness", daemon=True)

    def start(self) -> ReadinessWatch:
        self._thread.start()
        return self

    def stop(self, all_ready: bool = False) -> None:
        """Stop watching; all_ready: the caller saw every role alive, so report the ones not reported yet."""
        self._stop.set()
        self._thread.join(5)
        if all_ready:
            for role in self.roles:
                self._seen(role)

    def _seen(self, role: str) -> None:
        with self._lock:
            if role in self.seen:
                return
            self.seen.add(role)
        self.report(role, round(time.monotonic() - self.t0, 1))

    def _run(self) -> None:
        from occvo_services.sessions import open_session

        session = None
        while session is None and not self._stop.wait(0.2):
            try:
                session = open_session(self.ep, base=self.login, pick_up=self.login is None)
            except Exception:  # noqa: BLE001 - the router is not up yet
                session = None
        if session is None:
            return
        warming = False
        try:
            while not self._stop.is_set() and set(self.roles) - self.seen:
                try:
                    alive = {
                        str(r.ok.key_expr).split("/")[2]
                        for r in session.liveliness().get(keys.alive("*", "*"), timeout=1.0)
                        if r.ok
                    }
                except Exception:  # noqa: BLE001 - a lost router ends the watch
                    return
                for role in [r for r in self.roles if r in alive]:
                    self._seen(role)
                if not warming and "registration" not in self.seen and self.seen >= set(self.roles) - {"registration"}:
                    warming = True
                    self.report("warm-up", round(time.monotonic() - self.t0, 1))
                self._stop.wait(0.2)
        finally:
            session.close()


LOOPBACK_HOSTS = ("localhost", "::1", "[::1]")


def is_loopback(ep: str) -> bool:
    """tcp/127.0.0.1:7447, tls/localhost:7447, tcp/[::1]:7447; unix sockets are local too."""
    proto, _, addr = ep.split("#")[0].partition("/")
    if proto.startswith("unix"):
        return True
    host = addr.rpartition(":")[0] or addr
    return host in LOOPBACK_HOSTS or host.startswith("127.")


def listen_endpoints(router_config: str | Path) -> list[str]:
    """Every listen endpoint of a router config (all of them are checked, not only the one clients dial)."""
    import json5

    try:
        with open(router_config) as f:
            eps = json5.load(f).get("listen", {}).get("endpoints", [])
    except (OSError, ValueError) as exc:
        raise ConfigError(f"router config {router_config}: {exc}") from None
    if isinstance(eps, dict):  # per mode: {router: [...], peer: [...]}
        eps = [ep for group in eps.values() for ep in (group if isinstance(group, list) else [group])]
    return [eps] if isinstance(eps, str) else list(eps)


def check_listen_secure(router_config: str | Path, listen: list[str], insecure: bool) -> None:
    """A router listening beyond loopback must authenticate (user/password or mutual TLS, deploy/acl, deploy/tls)
    and control access: without authentication anyone on the network may replace a stored map or reset a stream,
    and authentication without access control lets any user (any certificate holder) do the same. --insecure says
    it is meant."""
    import json

    import zenoh

    open_eps = [ep for ep in listen if not is_loopback(ep)]
    if not open_eps or insecure:
        return
    c = zenoh.Config.from_file(str(router_config))
    usrpwd = json.loads(c.get_json("transport/auth/usrpwd/dictionary_file"))
    mtls = json.loads(c.get_json("transport/link/tls/enable_mtls"))
    if not usrpwd and not mtls:
        raise ConfigError(
            f"the router would listen on {', '.join(open_eps)} without authentication ({router_config} "
            "has neither transport/auth/usrpwd nor mutual TLS): use deploy/acl/router.json5 or "
            "deploy/tls/router.json5, listen on loopback, or pass --insecure"
        )
    if not json.loads(c.get_json("access_control/enabled")):
        raise ConfigError(
            f"the router would listen on {', '.join(open_eps)} with authentication but no access control "
            f"({router_config}: access_control is not enabled, so every user may do anything): use "
            "deploy/acl/router.json5 or deploy/tls/router.json5, listen on loopback, or pass --insecure"
        )


def add_identity_flags(p) -> None:
    """--anonymous and --insecure: two different things, said apart."""
    p.add_argument(
        "--anonymous",
        action="store_true",
        help="run the router without logins, as before: any process reaching it may connect, and a client is who it says "
        "it is (the workers' per-client guards are advisory then; docs/service.md). Default: logins and access "
        "control, the clients of this user logged in by themselves (occvo logins)",
    )
    p.add_argument(
        "--insecure",
        action="store_true",
        help="allow a listen endpoint beyond loopback on a router without authentication (with --anonymous or a "
        "--router-config of your own); nothing to do with logins on this machine",
    )


def secure_default(args, config, given_router: bool):
    """The authenticated default on an `occvo up` deployment (services/acl.py), unless --anonymous, a router
    config of the user's own, or no router here; returns the client config the command watches the workers with
    (None: any session). Says where the logins are, never a password."""
    from occvo_services import acl, logins

    args.logins_watch = None
    if getattr(args, "anonymous", False) or given_router or not config.router.enabled:
        return None
    folder = logins.logins_dir()
    try:
        probe = acl.authenticate(config, folder)
    except OSError as exc:
        raise ConfigError(f"logins folder {folder}: {exc.strerror or exc} (set ${logins.LOGINS_DIR_ENV})") from None
    # `occvo logins add/remove` while it runs: the router's config written again and the router restarted
    args.logins_watch = acl.LoginsWatch(folder, nodes=acl.ros2_nodes(config))
    own = logins.default_login()
    who = own if logins.session_file(own, folder).is_file() else logins.login_of(probe)
    progress(
        args,
        f"clients log in as {who} by themselves ({logins.session_file(who, folder)}); streams are {who}.<name>; "
        f"`occvo logins add NAME` makes a login for another user or host",
    )
    if any(w.role == "ros2" for w in config.workers):
        robots = ", ".join(logins.ros2_logins(folder)) or "none yet"
        progress(
            args,
            f"the ROS 2 node logs in as {logins.NODE_LOGIN}; a robot's rmw_zenoh logs in with a login of `occvo "
            f"logins add NAME --ros2` ({robots}; docs/ros2.md)",
        )
    return str(probe)


def deploy_dir() -> Path:
    """The source tree's deploy/ folder (deployment files; the package's built-in defaults live in services/defaults)."""
    return Path(__file__).resolve().parents[2] / "deploy"
