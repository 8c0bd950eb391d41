"""Typed errors: each names what was wrong and, for frames, which frame."""

from __future__ import annotations


class OccVOError(Exception):
    """Base of every error occvo raises on purpose."""


class InvalidFrameError(OccVOError, ValueError):
    """An occupancy frame that cannot be registered; the odometry state is left as it was."""

    def __init__(self, frame: object, reason: str):
        self.frame = frame
        self.reason = reason
        super().__init__(f"frame {frame}: {reason}")


class DatasetError(OccVOError, OSError):
    """A scene source, file or trajectory that cannot be read."""

    def __init__(self, path: object, reason: str):
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class ConfigError(OccVOError, ValueError):
    """A configuration that cannot be used."""
