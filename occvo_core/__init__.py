"""occvo_core: OCC-VO's algorithms (no transport).

The names below load on first use, so a light module (occvo_core.grid, which schemas reads) does not pull in the
compiled odometry."""

from importlib import import_module

_EXPORTS = {
    "OccVO": "occvo_core.odometry",
    "Registration": "occvo_core.odometry",
    "StepResult": "occvo_core.odometry",
    "OccVOConfig": "occvo_core.config",
    "OccupancyFrame": "occvo_core.frame",
    "OccVOError": "occvo_core.errors",
    "InvalidFrameError": "occvo_core.errors",
    "DatasetError": "occvo_core.errors",
    "ConfigError": "occvo_core.errors",
}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'occvo_core' has no attribute {name!r}")
    return getattr(import_module(_EXPORTS[name]), name)
