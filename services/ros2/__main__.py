"""`python -m occvo_services.ros2 [--config ros2.json5] [--connect tcp/host:7447] [--domain-id N] ...`: occvo's ROS 2
node on the service's router (`occvo serve --ros2` starts it); SIGTERM or Ctrl-C leaves the graph and exits 0."""

from __future__ import annotations

import argparse
import faulthandler
import os
import signal
import sys
import threading

import zenoh

from occvo_core.errors import ConfigError
from occvo_services.logins import login_of
from occvo_services.sessions import ZENOH_CONFIG_ENV, NoRouterError, zenoh_config
from occvo_services.stop_signals import set_on_signal
from occvo_services.telemetry import log_event, structured_logger
from occvo_services.worker_config import DEFAULT_ENDPOINT


def _open(connect: str) -> zenoh.Session:
    """A client session stamping its samples: a latched topic's cache (zenoh-ext) orders its samples by time."""
    try:
        c = zenoh_config("client", connect=connect)
        c.insert_json5("timestamping/enabled", "true")
    except zenoh.ZError as exc:
        raise ConfigError(f"{connect} is not a router endpoint: {exc}") from None
    try:
        return zenoh.open(c)
    except zenoh.ZError:
        raise NoRouterError(f"no router at {connect} (or it refused this session): start `occvo serve`") from None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m occvo_services.ros2", description=__doc__)
    p.add_argument("--config", help="json5 with the node's settings (docs/ros2.md)")
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, help=f"router endpoint (default {DEFAULT_ENDPOINT})")
    p.add_argument("--worker-id", default="ros2")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default 0)")
    p.add_argument("--namespace", help="the node's namespace (default /)")
    p.add_argument("--input", choices=["occupancy", "cameras"], help="which ROS input feeds the odometry")
    p.add_argument("--log-level", help="DEBUG, INFO, WARNING or ERROR (default: the settings', INFO)")
    args = p.parse_args(argv)
    try:
        from occvo_services.ros2.config import Ros2NodeConfig

        config = Ros2NodeConfig.load(
            args.config, domain_id=args.domain_id, namespace=args.namespace, input=args.input, log_level=args.log_level
        )
        from occvo_services.ros2.node import OccVONode  # rosbags (the `ros` extra) from here on

        session = _open(args.connect)
    except (ConfigError, NoRouterError) as exc:
        print(f"occvo ros2: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:
        print(f"occvo ros2: {exc.name} is missing: pip install 'occvo[ros]'", file=sys.stderr)
        return 2
    log = structured_logger(f"occvo.{args.worker_id}", config.log_level)
    faulthandler.register(signal.SIGUSR1)  # `kill -USR1 <pid>`: every thread's stack on stderr
    stop = threading.Event()
    set_on_signal(stop)
    # logged in (`occvo serve --ros2` on its logins: login ros2), its stream carries the login's prefix
    node = OccVONode(session, config, log, login=login_of(os.environ.get(ZENOH_CONFIG_ENV)))
    log_event(
        log,
        "ros2 node up",
        node=config.node_name,
        namespace=config.namespace,
        domain_id=config.domain_id,
        input=config.input,
        stream=node.client.stream,
    )
    stop.wait()
    node.close()
    session.close()
    log_event(log, "ros2 node stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
