"""Python client of the occvo service over Zenoh.

    with OccVOClient("tcp/127.0.0.1:7447", stream="car0") as env:
        env.reset()
        for frame in scene:                 # OccupancyFrame (replayed occupancy) or CameraFrame
            pose = env.step(frame)          # PoseEstimate, like a Gymnasium env step
        tile = env.tile(0, 1)

Frames sent but not answered are sent again when the liveliness token of an inference worker or of the registration
worker of the stream's shard comes back (it restarted: the frames it held are lost; the registration worker's durable
state answers frames it already registered with their stored poses) or after `resend_after` seconds without any
answer. New frames wait meanwhile: one that overtook a lost frame would make it old. A pose that arrives twice is
kept once. A frame that closed a loop has its pose published twice: the odometry pose as soon as it is known, then
(status "relocalised") the pose on the map seen long ago, which replaces it in `poses` (step() returns the first).
The sending and resending is client_sends.FrameSender's; the gets are client_gets.py's.
"""

from __future__ import annotations

__all__ = ["OccVOClient", "ServiceError", "camera_frame_of"]

import threading
import time

import numpy as np
import zenoh

from occvo_core.frame import OccupancyFrame
from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import (
    CameraFrame,
    ErrorEvent,
    MapInfo,
    MapTile,
    PoseEstimate,
    Trajectory,
    WorkerHealth,
)
from occvo_services.camera_frames import camera_frame_of
from occvo_services.client_gets import region_tiles, replies
from occvo_services.client_sends import FrameSender
from occvo_services.logins import own_stream
from occvo_services.runtime import DEFAULT_ENDPOINT
from occvo_services.sessions import open_login

# the error events a client keeps, the latest: one that runs for hours on a bad input does not grow without end
MAX_ERRORS = 1000
# error events that leave a frame waiting for its pose: it is sent again every resend_after until the pose comes
PENDING_CODES = ("missing_seq", "seq_held", "not_stored", "store_unavailable", "stream_full")


class ServiceError(RuntimeError):
    """The service answered with an error event (or did not answer in time)."""

    def __init__(self, message: str, event: ErrorEvent | None = None):
        self.event = event
        super().__init__(message)


class OccVOClient:
    def __init__(
        self,
        connect: str = DEFAULT_ENDPOINT,
        stream: str = "default",
        timeout: float = 60.0,
        session: zenoh.Session | None = None,
        exact: bool = True,
        resend_after: float | None = 5.0,
        query_timeout: float = 2.0,
        login: str | None = None,
    ):
        """Logged in (the login `occvo serve` made for this user, picked up by itself; or `login`, that of a given
        `session`), the stream id on the wire carries the login's prefix: "car0" is `<login>.car0` (self.stream)."""
        self.exact = exact
        # a query waits at most this long for its answers: a queryable that never answers costs no more
        self.query_timeout = query_timeout
        self.resend_after = resend_after
        self.timeout = timeout
        self._own = session is None
        keys.check_stream(stream)
        session, login = (session, login) if session is not None else open_login(connect)
        self.session, self.login = session, login
        self.stream = stream = keys.check_stream(own_stream(stream, login))  # at most 64 characters with the prefix
        self._cv = threading.Condition()
        self.poses: dict[int, PoseEstimate] = {}
        self.arrived: dict[int, float] = {}  # seq -> time.perf_counter() its first pose arrived (latency figures)
        self.errors: list[ErrorEvent] = []
        self._seq = 0
        self._alive: set[str] = set()  # worker tokens seen (workers())
        self._alive_sub = None
        self._subs = [
            self.session.declare_subscriber(keys.pose(stream), self._on_pose),
            self.session.declare_subscriber(keys.errors(stream), self._on_error),
        ]
        self._sender = FrameSender(self.session, stream, resend_after)
        self._sn = 0  # the gets' source info's sequence number: the workers know this client by its session's zid

    # -- answers
    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            pose = decode(sample.payload.to_bytes(), PoseEstimate)
        except CodecError:
            return  # not ours to judge; the workers only publish valid poses
        self._sender.answered(pose.seq, in_order=True)  # before a waiter for the pose sends again
        with self._cv:
            if pose.status == "relocalised":  # a loop closed at this frame: its pose moved
                self.poses[pose.seq] = pose
            else:
                self.poses.setdefault(pose.seq, pose)  # a resent frame's pose comes again: keep the first
                self.arrived.setdefault(pose.seq, time.perf_counter())
            self._cv.notify_all()

    def _on_error(self, sample: zenoh.Sample) -> None:
        try:
            event = decode(sample.payload.to_bytes(), ErrorEvent)
        except CodecError:
            return
        if event.code == "stream_full":  # flow control, not an error: sent again from there (FrameSender)
            self._sender.full(event.seq)
            return
        # not answers: a gap before the frame, a jump held for its next frame, a write the store refused (the frame
        # stays unanswered and is sent again after resend_after, until its pose comes)
        if event.seq is not None and event.code not in PENDING_CODES:
            self._sender.answered(event.seq, in_order=False)
        with self._cv:
            self.errors.append(event)
            del self.errors[:-MAX_ERRORS]
            self._cv.notify_all()

    # -- sending (client_sends.FrameSender)
    @property
    def resends(self) -> int:
        return self._sender.resends

    @property
    def turned_away(self) -> int:
        """stream_full answers: frames a full queue turned away (sent again)."""
        return self._sender.turned_away

    def resend(self, first: int = 0) -> int:
        """Send every unanswered frame (from seq `first` on) again, in seq order; returns how many."""
        return self._sender.resend(first)

    # -- Gymnasium-style driving
    def reset(self) -> None:
        """The next step starts a new trajectory (seq 0): the service resets this stream's odometry and map."""
        with self._cv:
            self._seq = 0
            self.poses.clear()
            self.arrived.clear()
            self.errors.clear()
        self._sender.forget()

    def publish(self, frame: OccupancyFrame | CameraFrame) -> int:
        """Send one frame without waiting; returns its seq."""
        seq = self._seq
        msg = (
            frame.model_copy(update={"stream": self.stream, "seq": seq, "sent_at": time.time()})
            if isinstance(frame, CameraFrame)
            else camera_frame_of(frame, self.stream, seq, exact=self.exact)
        )
        payload = encode(msg)
        self._seq += 1
        self._sender.send(seq, payload, self.timeout)
        return seq

    def forget(self, through: int) -> None:
        """Drop the poses and arrival times of seqs up to `through`: a client that runs for hours and has used them
        keeps nothing it has sent on (a pose that comes again later is dropped with the next call)."""
        with self._cv:
            for kept in (self.poses, self.arrived):
                for seq in [s for s in kept if s <= through]:
                    del kept[seq]

    def put_encoded(self, payload: bytes) -> None:
        """An encoded camera frame of this stream sent as this client, not tracked (tools and tests: a resend, a
        frame of any seq). A stream takes frames only from the client that opened it (services/limits.py)."""
        self._sender.put_untracked(payload)

    def wait_pose(self, seq: int, timeout: float | None = None) -> PoseEstimate:
        """The pose of `seq`; ServiceError if a worker reported an error for that seq or nothing came in time."""
        deadline = time.monotonic() + (timeout or self.timeout)
        with self._cv:
            while True:
                if seq in self.poses:
                    return self.poses[seq]
                bad = [e for e in self.errors if e.seq == seq and e.code not in PENDING_CODES]
                if bad:
                    raise ServiceError(f"seq {seq}: {bad[0].code}: {bad[0].message}", bad[0])
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ServiceError(
                        f"no pose for seq {seq} of stream {self.stream} within {timeout or self.timeout} s"
                    )
                self._cv.wait(left)

    def step(self, frame: OccupancyFrame | CameraFrame) -> PoseEstimate:
        return self.wait_pose(self.publish(frame))

    # -- queries
    def _replies(
        self, selector: str, expect, payload: bytes | None, timeout: float | None = None, first: bool = False
    ) -> tuple[list, list[ErrorEvent]]:
        """A get's decoded answers and error replies within `timeout` (the client's query_timeout), as this client
        (services/client_gets.py)."""
        timeout = self.query_timeout if timeout is None else timeout
        return replies(self.session, self._source_info, self.stream, selector, expect, payload, timeout, first)

    def _source_info(self) -> zenoh.SourceInfo:
        """Names this client's session: the workers' query budgets are per client."""
        with self._cv:
            self._sn += 1
            return zenoh.SourceInfo(self.session.id, self._sn)

    def _get(self, selector: str, expect, payload: bytes | None = None, first: bool = True) -> list:
        out, errs = self._replies(selector, expect, payload, first=first)
        if not out and errs:
            raise ServiceError(f"{selector}: {errs[0].code}: {errs[0].message}", errs[0])
        return out

    def tile(self, ix: int, iy: int) -> MapTile:
        found = self._get(keys.map_tile(self.stream, ix, iy), MapTile)
        if not found:
            raise ServiceError(f"no reply for tile {ix},{iy} (is the map service up?)")
        return found[0]

    def region(
        self, ix_min: int | None = None, ix_max: int | None = None, iy_min: int | None = None, iy_max: int | None = None
    ) -> list[MapTile]:
        tiles, errs = region_tiles(self._replies, self.stream, ix_min, ix_max, iy_min, iy_max)
        if not tiles and errs:
            raise ServiceError(f"region of {self.stream}: {errs[0].code}: {errs[0].message}", errs[0])
        return tiles

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        tiles = self.region()
        if not tiles:
            return np.zeros((0, 3)), np.zeros(0, np.uint8)
        return (
            np.concatenate([t.points.to_numpy() for t in tiles]),
            np.concatenate([t.labels.to_numpy() for t in tiles]),
        )

    def map_info(self) -> MapInfo:
        found = self._get(keys.map_info(self.stream), MapInfo)
        if not found:
            raise ServiceError("no map info reply (is the map service up?)")
        return found[0]

    def pose_latest(self) -> PoseEstimate:
        found = self._get(keys.pose_latest(self.stream) + "?version=2", PoseEstimate)  # v1 unless asked
        if not found:
            raise ServiceError("no pose/latest reply (is the registration worker up?)")
        return found[0]

    def trajectory(self) -> Trajectory:
        found = self._get(keys.trajectory(self.stream), Trajectory)
        if not found:
            raise ServiceError("no trajectory reply (is the registration worker up?)")
        return found[0]

    def stats(self, worker: str = "*") -> list[WorkerHealth]:
        return self._get(keys.stats(worker), WorkerHealth, first=False)

    def workers(self) -> list[str]:
        """Keys of the live workers' liveliness tokens: those the client has seen come and not go, and those a
        liveliness query finds now (a query through a router may miss a token that is there)."""
        with self._cv:
            if self._alive_sub is None:
                self._alive_sub = self.session.liveliness().declare_subscriber(
                    keys.alive("*", "*"), self._on_worker_token, history=True
                )
        found = {str(r.ok.key_expr) for r in self.session.liveliness().get(keys.alive("*", "*"), timeout=5.0) if r.ok}
        with self._cv:
            return sorted(found | self._alive)

    def _on_worker_token(self, sample: zenoh.Sample) -> None:
        with self._cv:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(str(sample.key_expr))
            else:
                self._alive.discard(str(sample.key_expr))

    def wait_for_workers(self, roles=("inference", "registration", "map"), timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            alive = {k.split("/")[2] for k in self.workers()}
            if set(roles) <= alive:
                return
            time.sleep(0.1)
        raise ServiceError(f"workers {sorted(set(roles) - alive)} not alive after {timeout} s")

    def close(self) -> None:
        self._sender.close()
        for s in self._subs + ([self._alive_sub] if self._alive_sub is not None else []):
            s.undeclare()
        if self._own:
            self.session.close()

    def __enter__(self) -> OccVOClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
