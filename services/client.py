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
from occvo_services.logins import own_stream
from occvo_services.runtime import DEFAULT_ENDPOINT
from occvo_services.sessions import open_login
from occvo_services.wire import encoding

# error events that leave a frame waiting for its pose: it is sent again every resend_after until the pose comes
PENDING_CODES = ("missing_seq", "seq_held", "not_stored", "store_unavailable", "stream_full")
FULL_RETRY_S = 1.0  # a frame a full queue turned away is sent again at the stream's next pose, or after this


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
        self._unanswered: dict[int, bytes] = {}  # seq -> the encoded frame, until its pose or error comes back
        self._send_lock = threading.Lock()  # resends and new frames leave in seq order
        self._last_answer = time.monotonic()
        # live tokens of the workers a frame passes: inference, and registration of this stream's shard
        self._path: dict[str, set[str]] = {"inference": set(), "registration": set()}
        self._seen: set[str] = set()
        self._down = False  # a worker of the path left: hold new frames until it is back and the lost ones resent
        self._back_at: float | None = None
        self.resends = 0
        self.turned_away = 0  # stream_full answers: frames a full queue turned away (sent again)
        self._full: tuple[int, float] | None = None  # (first seq a full queue turned away, when), until resent
        self._alive: set[str] = set()  # worker tokens seen (workers())
        self._alive_sub = None
        self._subs = [
            self.session.declare_subscriber(keys.pose(stream), self._on_pose),
            self.session.declare_subscriber(keys.errors(stream), self._on_error),
            self.session.liveliness().declare_subscriber(keys.registration_shard(), self._on_alive, history=True),
            self.session.liveliness().declare_subscriber(keys.alive("inference"), self._on_alive, history=True),
        ]
        self._pub = self.session.declare_publisher(
            keys.camera(stream), encoding=encoding("camera_frame"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._sn = 0  # the source info's sequence number: the workers know this client by its session's zid
        self._closed = threading.Event()
        self._credit = threading.Event()  # a pose came while frames a full queue turned away wait: send them now
        self._resender = threading.Thread(target=self._resend_loop, name=f"occvo-resend-{stream}", daemon=True)
        self._resender.start()

    # -- subscriptions
    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            pose = decode(sample.payload.to_bytes(), PoseEstimate)
        except CodecError:
            return  # not ours to judge; the workers only publish valid poses
        with self._cv:
            if pose.status == "relocalised":  # a loop closed at this frame: its pose moved
                self.poses[pose.seq] = pose
            else:
                self.poses.setdefault(pose.seq, pose)  # a resent frame's pose comes again: keep the first
                self.arrived.setdefault(pose.seq, time.perf_counter())
            # poses come in seq order: an older frame still unanswered was dropped upstream (latest policy)
            for seq in [s for s in self._unanswered if s <= pose.seq]:
                del self._unanswered[seq]
            self._last_answer = time.monotonic()
            if self._full is not None:
                self._credit.set()
            self._cv.notify_all()

    def _on_error(self, sample: zenoh.Sample) -> None:
        try:
            event = decode(sample.payload.to_bytes(), ErrorEvent)
        except CodecError:
            return
        with self._cv:
            if event.code == "stream_full":  # flow control, not an error: sent again from there (_resend_loop)
                self.turned_away += 1
                if event.seq is not None:  # from the first unanswered on: the frame it waits for may be earlier
                    self._full = (min(self._unanswered, default=event.seq), time.monotonic())
                return
            self.errors.append(event)
            # not answers: a gap before the frame, a jump held for its next frame, a write the store refused (the
            # frame stays unanswered and is sent again after resend_after, until its pose comes)
            if event.seq is not None and event.code not in PENDING_CODES:
                self._unanswered.pop(event.seq, None)
                self._last_answer = time.monotonic()
            self._cv.notify_all()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        shard = keys.parse_registration_shard(key)
        # shards 0: placement "members", where any registration worker may hold this stream
        if shard is not None and shard[1] and keys.shard_of(self.stream, shard[1]) != shard[0]:
            return  # another shard's worker: its coming and going does not touch this stream
        role = "inference" if shard is None else "registration"
        live = self._path[role]
        with self._cv:
            if sample.kind == zenoh.SampleKind.PUT:
                fresh = key not in live
                live.add(key)
                self._seen.add(role)
                if fresh and (self._down or self._unanswered) and self._path_up():
                    self._back_at = time.monotonic()  # a (re)started worker: resend what it cannot have seen
            else:
                live.discard(key)
                self._down = True  # even with another worker of its role up, the frames it held are lost
                self._back_at = time.monotonic() if self._path_up() else None
            self._cv.notify_all()

    def _path_up(self) -> bool:
        """Every role of the path that was ever seen has a live worker (a role never seen is not waited for)."""
        return all(live or role not in self._seen for role, live in self._path.items())

    # -- resending what a restarted worker lost
    def _resend_loop(self, settle_s: float = 0.3) -> None:
        while not self._closed.is_set():
            self._credit.wait(0.1)
            self._credit.clear()
            if self.resend_after is None:
                continue
            if self._full_due():
                continue
            with self._cv:
                now = time.monotonic()
                # back: its subscriptions have reached the router by now (they are declared before its token)
                back = self._back_at is not None and now - self._back_at >= settle_s
                stalled = bool(self._unanswered) and not self._down and now - self._last_answer >= self.resend_after
                if not (back or stalled):
                    continue
                self._last_answer = now
            self.resend()  # frames in flight while it was away were lost; nothing new went out meanwhile
            if back:
                with self._cv:
                    self._down, self._back_at = False, None
                    self._cv.notify_all()

    def _full_due(self) -> bool:
        """Frames a full queue turned away sent again, in order, once a pose freed room (or after FULL_RETRY_S)."""
        with self._cv:
            if self._full is None:
                return False
            k, at = self._full
            if self._last_answer <= at and time.monotonic() - at < FULL_RETRY_S:
                return False
            self._full = None
            self._cv.notify_all()
        self.resend(k)
        return True

    def resend(self, first: int = 0) -> int:
        """Send every unanswered frame (from seq `first` on) again, in seq order; returns how many."""
        with self._send_lock:
            with self._cv:
                pending = sorted((seq, p) for seq, p in self._unanswered.items() if seq >= first)
            for _, payload in pending:
                self._put(payload)
            self.resends += len(pending)
            return len(pending)

    # -- Gymnasium-style driving
    def reset(self) -> None:
        """The next step starts a new trajectory (seq 0): the service resets this stream's odometry and map."""
        with self._cv:
            self._seq = 0
            self.poses.clear()
            self.arrived.clear()
            self.errors.clear()
            self._unanswered.clear()

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
        with self._cv:  # while a worker of the path is away, a new frame would overtake the lost ones
            deadline = time.monotonic() + self.timeout
            # and while frames a full queue turned away wait to go again: the new one would be turned away too
            while (
                (self._down or self._full is not None) and self.resend_after is not None and time.monotonic() < deadline
            ):
                self._cv.wait(0.1)
        with self._send_lock:
            with self._cv:
                if not self._unanswered:
                    self._last_answer = time.monotonic()  # the resend clock runs from the oldest frame in flight
                self._unanswered[seq] = payload
            self._put(payload)
        return seq

    def _put(self, payload: bytes) -> None:
        """A frame out, with the source info that names this client's session (services/limits.py); under _send_lock."""
        self._sn += 1
        self._pub.put(payload, source_info=zenoh.SourceInfo(self._pub.id, self._sn))

    def put_encoded(self, payload: bytes) -> None:
        """An encoded camera frame of this stream sent as this client, not tracked (tools and tests: a resend, a
        frame of any seq). A stream takes frames only from the client that opened it (services/limits.py)."""
        with self._send_lock:
            self._put(payload)

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
        self._closed.set()
        self._credit.set()
        self._resender.join(timeout=5)
        for s in self._subs + ([self._alive_sub] if self._alive_sub is not None else []):
            s.undeclare()
        self._pub.undeclare()
        if self._own:
            self.session.close()

    def __enter__(self) -> OccVOClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
