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
