"""What the registration worker keeps of one stream."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from occvo_schemas.models import PoseEstimate
from occvo_services.store import StoredPose


class StreamState:
    """One stream: its OccVO (None until this process registered or resumed it) and what queries read."""

    def __init__(self):
        self.vo = None
        self.lock = threading.Lock()  # guards the lists and `latest`; only the stream's lane touches vo
        self.seqs: list[int] = []
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.statuses: list[str] = []
        self.digests: list[bytes] = []
        self.position: dict[int, int] = {}  # seq -> index in the lists
        self.latest: PoseEstimate | None = None
        self.tiles: dict = {}  # published tiles of the working map
        self.started = False  # a trajectory exists (in memory or in the store)
        self.cold: dict[tuple[int, int], list[int]] = {}  # evicted tile -> seqs it was evicted at (its store rows)
        self.cold_digest: dict[tuple[int, int], bytes] = {}  # published content of an evicted tile
        self.pending_restored: list[tuple[int, int, int]] = []  # restored, not yet stored (finish_frame)
        self.since_snapshot = 0
        self.snapshot_since = time.monotonic()  # the stream's start, resume or last snapshot: what its share is of
        self.snapshot_idle = threading.Event()  # no snapshot of this stream queued or being written
        self.snapshot_idle.set()
        self.snapshot_retry = False  # the last snapshot failed: take one at the next frame
        self.send_all_tiles = False  # after a resume: the map service may lack the last frames' tiles
        self.entered = 0  # frames that entered the lane: the work after a pose sees whether another came
        self.map_cut_at = -np.inf  # time.monotonic() of the last cut of the map for tiles
        self.map_pending = False  # the map changed since that cut (its tiles go out with a later frame's)
        self.tiling_ms = self.complete_ms = self.extract_ms = 0.0
        self.restore_ms = self.evict_ms = 0.0  # the last step's working-map restores and evictions
        self.restored_for_next: list[tuple[int, int]] = []  # tiles restored after the last frame, not yet published
        self.ego_xy: np.ndarray | None = None  # x-y of the last registered pose (eviction and restore centre)
        self.after_pose: ThreadPoolExecutor | None = None  # the stream's thread for the work after a pose
        self.tail = None  # Future of the last frame's work after its pose
        # set: that work may start (a frame came in, or the pose had its head start: StreamLanes._register_frame)
        self.head_start = threading.Event()
        self.head_start.set()
        self.map_thread: ThreadPoolExecutor | None = None  # the stream's thread cutting and sending its map tiles
        self.map_tail = None  # Future of the last frame's tiles (st.tiles, cold_digest, send_all_tiles are its)
        self.tail_lock = threading.Lock()  # orders the lane's priority boost against the end of that work
        self.tail_running = False
        self.tail_tid: int | None = None  # native id of the after-pose thread
        self.tail_boosted = False  # that thread runs at the lane's priority (the lane waits for it)

    def append(self, seq: int, stamp: float, pose: np.ndarray, status: str, digest: bytes) -> None:
        self.position[seq] = len(self.seqs)
        self.seqs.append(seq)
        self.stamps.append(stamp)
        self.poses.append(pose)
        self.statuses.append(status)
        self.digests.append(digest)

    def clear(self) -> None:
        self.seqs, self.stamps, self.poses, self.statuses, self.digests, self.position = [], [], [], [], [], {}

    def stored(self, seq: int) -> StoredPose | None:
        i = self.position.get(seq)
        return None if i is None else StoredPose(seq, self.stamps[i], self.digests[i], self.statuses[i], self.poses[i])
