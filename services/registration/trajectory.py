"""A stream's trajectory as the registration worker serves it: every committed pose, in seq order, for resends and
queries."""

from __future__ import annotations

import threading
import time

import numpy as np

from occvo_schemas.models import PoseEstimate
from occvo_services.store.records import StoredPose


class StreamTrajectory:
    """Committed poses of one stream (in memory; the store has them too). Its lock guards the lists and `latest`: the
    session writes them; queries from other threads read what latest_pose() and arrays() hand out."""

    def __init__(self):
        self._lock = threading.Lock()
        self.seqs: list[int] = []
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.statuses: list[str] = []
        self.digests: list[bytes] = []
        self.position: dict[int, int] = {}  # seq -> index in the lists
        self.latest: PoseEstimate | None = None
        self.started = False  # a trajectory exists (in memory or in the store)

    def append(self, seq: int, stamp: float, pose: np.ndarray, status: str, digest: bytes) -> None:
        self.position[seq] = len(self.seqs)
        self.seqs.append(seq)
        self.stamps.append(stamp)
        self.poses.append(pose)
        self.statuses.append(status)
        self.digests.append(digest)

    def record(self, pose: PoseEstimate, pose_m: np.ndarray, digest: bytes, restart: bool) -> None:
        """A published pose: a new trajectory's first, the next one, or a relocalised pose replacing its seq's."""
        with self._lock:
            if restart:
                self.seqs, self.stamps, self.poses, self.statuses, self.digests, self.position = [], [], [], [], [], {}
                self.started = True
            i = self.position.get(pose.seq)
            if i is not None:
                self.poses[i], self.statuses[i] = pose_m, pose.status
            else:
                self.append(pose.seq, pose.stamp, pose_m, pose.status, digest)
            self.latest = pose

    def latest_pose(self) -> PoseEstimate | None:
        """The last published pose (a query's answer)."""
        with self._lock:
            return self.latest

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(seqs, stamps, 4x4 poses) as they are now, copied (a query's answer)."""
        with self._lock:
            return (
                np.array(self.seqs, np.int64),
                np.array(self.stamps, np.float64),
                np.array(self.poses, np.float64).reshape(-1, 4, 4),
            )

    @property
    def last_seq(self) -> int:
        return self.seqs[-1]

    def stored(self, seq: int) -> StoredPose | None:
        i = self.position.get(seq)
        return None if i is None else StoredPose(seq, self.stamps[i], self.digests[i], self.statuses[i], self.poses[i])


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
