"""The `occvo` command line: offline commands (occvo_cli.commands) and the service commands (occvo_services.commands)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("occvo")
except PackageNotFoundError:  # a source tree on PYTHONPATH, not installed
    __version__ = "0+unknown"
