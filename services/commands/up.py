"""occvo up: the router and workers of a json5 file (deploy/occvo.json5), restarted when they crash; Ctrl-C stops all."""

from __future__ import annotations

import json

from services.commands._common import DEPLOY, check_listen_secure


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("up", help="run and supervise the router and workers named in a json5 file")
    p.add_argument("--config", default=str(DEPLOY / "occvo.json5"), help="deployment json5 (default deploy/occvo.json5)")
    p.add_argument("--listen", help="replace the router's listen endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--log-dir", help="each child's log to <dir>/<name>.log (default: stderr)")
    p.add_argument("--insecure", action="store_true", help="allow a non-loopback listen endpoint without authentication")
    p.set_defaults(func=run)


def run(args) -> int:
    from services.supervisor import Supervisor, UpConfig

    config = UpConfig.load(args.config)
    if args.listen:
        config.router.listen, config.router.connect = args.listen, None
    if args.log_dir:
        config.log_dir = args.log_dir
    if config.router.enabled:
        import json5

        router_file = config.router.config or str(DEPLOY / "router.json5")
        listen = [config.router.listen] if config.router.listen else json5.load(open(router_file))["listen"]["endpoints"]
        check_listen_secure(router_file, listen, args.insecure)
    sup = Supervisor(config)

    def ready(s: Supervisor) -> None:
        print(json.dumps({"event": "ready", "endpoint": s.endpoint, "pids": s.pids()}), flush=True)

    code = sup.run(ready)
    print(json.dumps({"event": "stopped", "code": code}), flush=True)
    return code
