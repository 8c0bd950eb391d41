"""Argument types for the paths a command writes: checked when the command line is read, so a path that cannot be
written is a usage error (exit 2, one line) before any work, not a failure after it."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def _nearest_existing(path: Path) -> Path:
    path = path.absolute()
    while not path.exists():
        path = path.parent
    return path


def _writable_folder(path: Path, what: str) -> None:
    """path's nearest existing ancestor is a folder this process may write into (that is where the rest is made)."""
    base = _nearest_existing(path)
    if not base.is_dir():
        raise argparse.ArgumentTypeError(f"{what}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{what}: no permission to write in {base}")


def out_dir(text: str) -> Path:
    """A folder to write into: an existing folder, or a path whose folders can be made."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder: name a folder")
    _writable_folder(path, text)
    return path


def out_file(make_parents: bool = False, kind: type = Path):
    """A file to write: not a folder; its folder must exist, unless the writer makes it (make_parents). The value
    is kind(text) (str where a command has always handed the name on as given)."""

    def check(text: str):
        path = Path(text)
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{text} is a folder: name a file")
        if not make_parents and not path.absolute().parent.exists():
            raise argparse.ArgumentTypeError(f"{text}: no folder {path.absolute().parent}")
        _writable_folder(path.absolute().parent, text)
        return kind(text)

    check.__name__ = "out_file"  # argparse names the type in its messages
    return check
