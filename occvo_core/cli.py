"""The `occvo` command: one subcommand a module, each with add_parser(subparsers) and run(args) -> int."""

from __future__ import annotations

import argparse
import importlib
import sys

from occvo_core.errors import OccVOError

CORE_COMMANDS = ["run", "eval", "ablation", "eval_map", "train_occ", "eval_occ"]


def _command_modules():
    for name in CORE_COMMANDS:
        try:
            yield importlib.import_module(f"occvo_core.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"occvo_core.commands.{name}":
                raise
    try:  # the service commands live with the services, which depend on the transport
        services = importlib.import_module("services.commands")
    except ModuleNotFoundError as exc:
        if exc.name not in ("services", "services.commands"):
            raise
        return
    for name in services.COMMANDS:
        yield importlib.import_module(f"services.commands.{name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="occvo", description="OCC-VO: 3D-occupancy visual odometry and semantic mapping")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in _command_modules():
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except OccVOError as exc:
        print(f"occvo {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"occvo {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
