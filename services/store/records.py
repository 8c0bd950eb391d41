"""What the store hands back: a stored pose, a stream's record, a lease; and the pose's bytes in a row."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class StoredPose:
    seq: int
    stamp: float
    digest: bytes
    status: str
    pose: np.ndarray  # 4x4


@dataclass
class StreamRecord:
    stream: str
    created: float
    last_seq: int | None
    snapshot_seq: int | None


@dataclass(frozen=True)
class Lease:
    stream: str
    owner: str | None  # None: released
    epoch: int
    remaining_s: float  # until it expires (<= 0: expired), by the database's clock


def pose_bytes(pose: np.ndarray) -> bytes:
    """A 4x4 pose as its row keeps it: float64, row-major."""
    return np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes()


def stored_pose(row) -> StoredPose:
    """A StoredPose of a (seq, stamp, digest, status, pose) row."""
    seq, stamp, digest, status, blob = row
    return StoredPose(
        int(seq), float(stamp), bytes(digest), status, np.frombuffer(blob, np.float64).reshape(4, 4).copy()
    )


SIZES = ("poses", "snapshots", "journal", "cold_tiles")  # the tables a stream's sizes count, in this order
