"""Built-in configs of the router and every worker, shipped inside the package so an installed `occvo serve` and
`occvo up` run from any directory. The files under deploy/ are the deployment copies that override them
(`--config` / `--router-config`)."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

NAMES = (
    "router.json5",
    "acl_router.json5",
    "inference_worker.json5",
    "registration_worker.json5",
    "map_service.json5",
    "occvo.json5",
)


def path(name: str) -> Path:
    """A built-in config as a file path (zenoh and the workers read files; the package is installed unzipped)."""
    if name not in NAMES:
        raise KeyError(f"no built-in config {name!r}; there are {', '.join(NAMES)}")
    return Path(str(files(__name__) / name))
