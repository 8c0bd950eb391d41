"""Arguments every service command shares: where the router is, which stream."""

from __future__ import annotations

from pathlib import Path

from services.runtime import DEFAULT_ENDPOINT, router_endpoint

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def add_connection(p, stream: bool = True) -> None:
    p.add_argument("--connect", help=f"router endpoint (default: listen endpoint of --router-config, else {DEFAULT_ENDPOINT})")
    p.add_argument("--router-config", default=None, help="router json5 config (default deploy/router.json5)")
    if stream:
        p.add_argument("--stream", default="default", help="stream id (default: default)")


def endpoint(args) -> str:
    if getattr(args, "connect", None):
        return args.connect
    cfg = args.router_config or (DEPLOY / "router.json5")
    return router_endpoint(cfg) if Path(cfg).is_file() else DEFAULT_ENDPOINT


LOOPBACK_HOSTS = ("localhost", "::1", "[::1]")


def is_loopback(ep: str) -> bool:
    """tcp/127.0.0.1:7447, tls/localhost:7447, tcp/[::1]:7447; unix sockets are local too."""
    proto, _, addr = ep.split("#")[0].partition("/")
    if proto.startswith("unix"):
        return True
    host = addr.rpartition(":")[0] or addr
    return host in LOOPBACK_HOSTS or host.startswith("127.")


def check_listen_secure(router_config: str | Path, listen: list[str], insecure: bool) -> None:
    """A router listening beyond loopback must authenticate (user/password or mutual TLS, deploy/acl, deploy/tls):
    without it anyone on the network may replace a stored map or reset a stream. --insecure says it is meant."""
    import json

    import zenoh

    from occvo_core.errors import ConfigError

    open_eps = [ep for ep in listen if not is_loopback(ep)]
    if not open_eps or insecure:
        return
    c = zenoh.Config.from_file(str(router_config))
    usrpwd = json.loads(c.get_json("transport/auth/usrpwd/dictionary_file"))
    mtls = json.loads(c.get_json("transport/link/tls/enable_mtls"))
    if not usrpwd and not mtls:
        raise ConfigError(f"the router would listen on {', '.join(open_eps)} without authentication ({router_config} "
                          "has neither transport/auth/usrpwd nor mutual TLS): use deploy/acl/router.json5 or "
                          "deploy/tls/router.json5, listen on loopback, or pass --insecure")
