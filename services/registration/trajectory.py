"""A stream's trajectory as the registration worker serves it: every committed pose, in seq order, for resends and
queries. The pose path writes it; queries read the TrajectoryView it publishes after each pose (no lock)."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from occvo_schemas.models import PoseEstimate
from occvo_services.store.records import StoredPose


class TrajectoryView(NamedTuple):
    """The trajectory as published after a pose: what queries read from other threads. Its arrays are never written
    after it is published (a relocalised pose or a new trajectory writes new arrays)."""

    latest: PoseEstimate
    seqs: np.ndarray
    stamps: np.ndarray
    poses: np.ndarray  # (n, 4, 4)

    @property
    def last_seq(self) -> int:
        return int(self.seqs[-1]) if len(self.seqs) else -1

    def has(self, seq: int) -> bool:
        i = int(np.searchsorted(self.seqs, seq))  # seqs ascend within a trajectory
        return i < len(self.seqs) and self.seqs[i] == seq


class StreamTrajectory:
    """Committed poses of one stream (in memory; the store has them too), written by its session's pose path only.
    Rows grow in place past the published ones; a row published is replaced in a copy (copy on write)."""

    def __init__(self):
        self.view: TrajectoryView | None = None  # None until a pose is known (in memory or in the store)
        self._clear()

    def _clear(self) -> None:
        self._seqs, self._stamps, self._poses = _rows(0)
        self._n = 0
        self._statuses: list[str] = []
        self._digests: list[bytes] = []
        self._position: dict[int, int] = {}  # seq -> row

    def __len__(self) -> int:
        return self._n

    def append(self, seq: int, stamp: float, pose: np.ndarray, status: str, digest: bytes) -> None:
        """A pose after the last (the rows past the published ones: no reader sees them)."""
        n = self._n
        if n == len(self._seqs):  # full: rows twice as many, the published ones copied (readers keep the old)
            grown = _rows(max(64, 2 * n))
            for new, old in zip(grown, (self._seqs, self._stamps, self._poses), strict=True):
                new[:n] = old
            self._seqs, self._stamps, self._poses = grown
        self._seqs[n], self._stamps[n], self._poses[n] = seq, stamp, pose
        self._position[seq] = n
        self._statuses.append(status)
        self._digests.append(digest)
        self._n = n + 1

    def record(self, pose: PoseEstimate, pose_m: np.ndarray, digest: bytes, restart: bool) -> None:
        """A published pose: a new trajectory's first, the next one, or a relocalised pose replacing its seq's."""
        if restart:
            self._clear()
        i = self._position.get(pose.seq)
        if i is not None:
            self._poses = self._poses.copy()  # the published arrays stay as queries read them
            self._poses[i], self._statuses[i] = pose_m, pose.status
        else:
            self.append(pose.seq, pose.stamp, pose_m, pose.status, digest)
        self.publish(pose)

    def publish(self, latest: PoseEstimate) -> None:
        n = self._n
        self.view = TrajectoryView(latest, self._seqs[:n], self._stamps[:n], self._poses[:n])

    @property
    def started(self) -> bool:
        """A trajectory exists (in memory or in the store)."""
        return self.view is not None

    @property
    def last_seq(self) -> int:
        return int(self._seqs[self._n - 1])

    def stored(self, seq: int) -> StoredPose | None:
        i = self._position.get(seq)
        if i is None:
            return None
        return StoredPose(seq, float(self._stamps[i]), self._digests[i], self._statuses[i], self._poses[i])


def _rows(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.empty(n, np.int64), np.empty(n, np.float64), np.empty((n, 4, 4), np.float64)


def pose_message(stream: str, p: StoredPose) -> PoseEstimate:
    """A committed pose as published again (a resend's answer, a query's)."""
    return PoseEstimate(
        stream=stream,
        seq=p.seq,
        stamp=p.stamp,
        pose=np.asarray(p.pose, float).tolist(),
        status=p.status,
        timings_ms={},
        sent_at=time.time(),
    )
