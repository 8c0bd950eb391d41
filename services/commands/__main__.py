"""`python -m services.commands <command> ...`: the service commands without the top-level `occvo` CLI."""

import argparse
import importlib
import sys

from services.commands import COMMANDS


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.commands")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"services.commands.{name}").add_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
