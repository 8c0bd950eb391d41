"""The `occvo` command: parser and dispatch. One subcommand a module, each with add_parser(subparsers) and
run(args) -> int.

Every command keeps one convention: results on stdout (`--json`: machine-readable), progress and errors on stderr,
an error as one line naming what is wrong and what to do, exit code 2 for bad input or usage, 1 for a failure at
run time, no traceback unless --debug.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import os
import signal
import sys
import threading
import weakref

from occvo_cli import __version__
from occvo_cli.commands import COMMANDS
from occvo_core import OccVOError

BAD_INPUT, FAILED, INTERRUPTED = 2, 1, 130


class Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one line (argparse prints the whole usage block first)."""

    def error(self, message: str):
        self.exit(BAD_INPUT, f"{self.prog}: error: {message.splitlines()[0]} (see {self.prog} --help)\n")

    def parse_args(self, args=None, namespace=None):
        """argparse reports a subcommand's unknown flags from the top parser, naming neither the subcommand nor the
        flag meant: they are reported by the subcommand's parser, with the closest flags it has."""
        parsed, unknown = self.parse_known_args(args, namespace)
        if unknown:
            sub = getattr(self, "commands", {}).get(getattr(parsed, "command", None), self)
            sub.error(unknown_message(sub, unknown))
        return parsed


def unknown_message(parser: argparse.ArgumentParser, unknown: list[str]) -> str:
    flags = [a.split("=", 1)[0] for a in unknown if a.startswith("-")]
    if not flags:
        return f"unrecognized arguments: {' '.join(unknown)}"
    known = [s for a in parser._actions for s in a.option_strings if s.startswith("--")]
    named = []
    for flag in flags:
        meant = difflib.get_close_matches(flag, known, n=1)
        named.append(f"{flag} (did you mean {meant[0]}?)" if meant else flag)
    return f"unrecognized argument{'s' if len(named) > 1 else ''} {', '.join(named)}"


def _command_modules():
    for name in COMMANDS:
        yield importlib.import_module(f"occvo_cli.commands.{name}")
    try:  # the service commands live with the services, which need the transport (zenoh)
        services = importlib.import_module("occvo_services.commands")
    except ModuleNotFoundError as exc:
        if exc.name not in ("occvo_services", "occvo_services.commands", "zenoh"):
            raise
        return
    for name in services.COMMANDS:
        yield importlib.import_module(f"occvo_services.commands.{name}")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="occvo", description="OCC-VO: 3D-occupancy visual odometry and semantic mapping")
    parser.add_argument("--version", action="version", version=f"occvo {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for module in _command_modules():
        module.add_parser(sub)
    parser.commands = sub.choices
    for p in sub.choices.values():  # --debug also after the command
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show the traceback of an error")
    return parser


def exit_code(exc: BaseException) -> int:
    """2 when the input was wrong (occvo's own typed errors say so), 1 for anything failing at run time."""
    return BAD_INPUT if isinstance(exc, OccVOError) else FAILED


def _worded() -> tuple[type, ...]:
    """Errors whose message is already the line for the user: occvo's own and the service client's."""
    try:
        from occvo_services.client import ServiceError
        from occvo_services.sessions import NoRouterError
    except ModuleNotFoundError:
        return (OccVOError,)
    return OccVOError, ServiceError, NoRouterError


def error_line(exc: BaseException) -> str:
    from occvo_services.store.url import redact  # a store's password is never printed (a driver may quote the URL)

    text = (redact(str(exc)).strip().splitlines() or [""])[0]
    if isinstance(exc, _worded()):
        return text
    if type(exc).__module__.split(".")[0] == "zenoh":  # its messages end in a Rust source path
        from occvo_services.sessions import zenoh_reason

        return f"the connection to the router failed: {zenoh_reason(exc)} (--debug shows the traceback)"
    return f"{text or type(exc).__name__} ({type(exc).__name__}; --debug shows the traceback)"


class _Sigint:
    """Ctrl-C raises KeyboardInterrupt as Python's own handler does, and is remembered: a KeyboardInterrupt raised
    inside a compiled (numba) call reaches Python as another error (a SystemError "returned a result with an
    exception set"), which is then still read as the interrupt it was."""

    received = False
    deferred = False  # received inside a callback from compiled code and sent again, not yet raised

    @classmethod
    def install(cls):
        """Returns the handler it replaced (None off the main thread, where signal handlers cannot be set)."""
        cls.received = cls.deferred = False
        if threading.current_thread() is threading.main_thread():
            return signal.signal(signal.SIGINT, cls._handle)
        return None

    @classmethod
    def _handle(cls, signum, frame):
        cls.received = True
        cls.deferred = frame is not None and f"{os.sep}llvmlite{os.sep}" in frame.f_code.co_filename
        if cls.deferred:
            # a callback from compiled code (numba's cache) would print the interrupt and swallow it: the signal is
            # sent again once the callback has returned
            again = threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT))
            again.daemon = True
            again.start()
            return
        raise KeyboardInterrupt


def interrupted(exc: BaseException) -> bool:
    """Whether exc is a Ctrl-C: a KeyboardInterrupt anywhere in its chain, or any error after a SIGINT arrived."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return _Sigint.received


def _end_progress_bars() -> None:
    """A progress bar left open ends its line first, so the error's line is a line of its own (a bar interrupted
    while it was being made is not among tqdm's bars yet: the line it left is ended too)."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())):
        bar = bar() if isinstance(bar, weakref.ref) else bar  # tqdm keeps its bars as weak references
        try:
            bar.close()
        except Exception:  # noqa: BLE001 - a bar that cannot close leaves its line as it is
            pass
    if isinstance(sys.stderr, _LineEnds) and not sys.stderr.at_line_start:
        sys.stderr.write("\n")


class _LineEnds:
    """stderr that knows whether its last write ended a line."""

    def __init__(self, stream):
        self._stream, self.at_line_start = stream, True

    def write(self, text: str) -> int:
        if text:
            self.at_line_start = text.endswith("\n")
        return self._stream.write(text)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    before = _Sigint.install()
    command, debug = "occvo", "--debug" in (sys.argv[1:] if argv is None else argv)
    stderr = sys.stderr
    if not isinstance(stderr, _LineEnds):
        sys.stderr = _LineEnds(stderr)
    try:
        args = build_parser().parse_args(argv)
        args.argv = sys.argv[1:] if argv is None else list(argv)  # the command as given, for run.json
        command, debug = f"occvo {args.command}", args.debug
        code = int(args.func(args) or 0)
        if _Sigint.deferred:  # the command ended before the Ctrl-C it got could be raised
            raise KeyboardInterrupt
        return code
    except BrokenPipeError:  # `occvo poses | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (KeyboardInterrupt, Exception) as exc:  # the one place every error becomes one line and an exit code
        _end_progress_bars()
        if interrupted(exc):
            if before is not None:
                signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C does not break the one line
            print(f"{command}: interrupted", file=sys.stderr)
            return INTERRUPTED
        if debug:
            raise
        print(f"{command}: error: {error_line(exc)}", file=sys.stderr)
        return exit_code(exc)
    finally:
        sys.stderr = stderr
        if before is not None:
            # a process that ends with main: a Ctrl-C from now on comes after the work is done (and must not turn
            # its exit into a traceback); main called in a process that goes on (a test): its own handler back
            signal.signal(signal.SIGINT, signal.SIG_IGN if argv is None else before)


if __name__ == "__main__":
    sys.exit(main())
