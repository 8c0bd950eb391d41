"""Trajectory files: KITTI (12 numbers a line, row-major 3x4) and TUM (stamp tx ty tz qx qy qz qw)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.errors import DatasetError


def _load_rows(path: Path, width: int, what: str) -> np.ndarray:
    try:
        rows = np.loadtxt(path, ndmin=2, comments="#")
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"cannot read {what} trajectory: {exc}") from None
    if rows.size == 0:
        raise DatasetError(path, f"empty {what} trajectory")
    if rows.shape[1] != width:
        raise DatasetError(path, f"{what} lines need {width} numbers, found {rows.shape[1]}")
    if not np.all(np.isfinite(rows)):
        raise DatasetError(path, f"{what} trajectory has non-finite numbers")
    return rows


def read_kitti(path: str | Path) -> np.ndarray:
    """(N,4,4) poses from a KITTI file."""
    rows = _load_rows(Path(path), 12, "KITTI")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows.reshape(-1, 3, 4)
    return poses


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    poses = np.asarray(poses)
    np.savetxt(path, poses[:, :3, :4].reshape(len(poses), 12), fmt="%.9e")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,), poses (N,4,4)) from a TUM file."""
    rows = _load_rows(Path(path), 8, "TUM")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], poses


def write_tum(path: str | Path, poses: np.ndarray, stamps: np.ndarray | None = None) -> None:
    poses = np.asarray(poses)
    stamps = np.arange(len(poses), dtype=float) if stamps is None else np.asarray(stamps, dtype=float)
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w as TUM wants
    np.savetxt(path, np.column_stack([stamps, poses[:, :3, 3], quat]), fmt="%.9f")


def read_trajectory(path: str | Path) -> np.ndarray:
    """Poses from a KITTI or TUM file, told apart by the number of columns."""
    return read_stamped_trajectory(path)[1]


def read_stamped_trajectory(path: str | Path) -> tuple[np.ndarray | None, np.ndarray]:
    """(stamps, poses) from a TUM file, (None, poses) from a KITTI file (it has no stamps)."""
    path = Path(path)
    try:
        first = next(l for l in path.read_text().splitlines() if l.strip() and not l.startswith("#"))
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read trajectory: {exc}") from None
    except StopIteration:
        raise DatasetError(path, "empty trajectory") from None
    width = len(first.split())
    if width == 12:
        return None, read_kitti(path)
    if width == 8:
        return read_tum(path)
    raise DatasetError(path, f"not a KITTI (12 numbers) or TUM (8 numbers) trajectory: first line has {width}")
