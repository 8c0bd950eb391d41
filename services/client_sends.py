"""A client's sends: its frames leave in seq order and are kept until answered; they go again when a worker of their
path comes back (its liveliness token), after `resend_after` seconds without an answer, or, the frames a full queue
turned away (stream_full) and only those, once a pose frees room. New frames wait meanwhile: one that overtook a lost
frame would make it old."""

from __future__ import annotations

import threading
import time

import zenoh

from occvo_schemas import keys
from occvo_services.wire import encoding

FULL_RETRY_S = 1.0  # a frame a full queue turned away is sent again at the stream's next pose, or after this
FULL_BURST = 8  # frames sent again at a time after stream_full (a stream's queues hold a few)


class FrameSender:
    """The frames of one client's stream in flight; the client tells it what was answered."""

    def __init__(self, session: zenoh.Session, stream: str, resend_after: float | None):
        self.stream, self.resend_after = stream, resend_after
        self._cv = threading.Condition()
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
        self._full: float | None = None  # when a full queue first turned a frame away since the last resend of them
        self._refused: set[int] = set()  # the frames a full queue turned away, not sent again since
        self._refused_at = 0.0  # the last stream_full
        self._subs = [
            session.liveliness().declare_subscriber(keys.registration_shard(), self._on_alive, history=True),
            session.liveliness().declare_subscriber(keys.alive("inference"), self._on_alive, history=True),
        ]
        self._pub = session.declare_publisher(
            keys.camera(stream), encoding=encoding("camera_frame"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._sn = 0  # the source info's sequence number: the workers know this client by its session's zid
        self._closed = threading.Event()
        self._credit = threading.Event()  # a pose came while frames a full queue turned away wait: send them now
        self._resender = threading.Thread(target=self._resend_loop, name=f"occvo-resend-{stream}", daemon=True)
        self._resender.start()

    # -- what the client tells it
    def answered(self, seq: int, in_order: bool) -> None:
        """An answer for `seq`: a pose (in_order: poses come in seq order, so an older frame still unanswered was
        dropped upstream, latest policy) or an error that ends the frame."""
        with self._cv:
            for s in [s for s in self._unanswered if s <= seq] if in_order else [seq]:
                self._unanswered.pop(s, None)
                self._refused.discard(s)
            self._last_answer = time.monotonic()
            if in_order and self._full is not None:
                self._credit.set()

    def full(self, seq: int | None) -> None:
        """stream_full: flow control, not an error; that frame is sent again (_full_due). Only the frames turned away:
        a copy of a frame a queue holds is turned away in its turn (the queue is full) and sent again, and resending
        from the first unanswered frame multiplied the frames an overloaded worker took in (five for each frame), until
        the puts blocked for seconds and the waits at the workers ran out. The retry's clock runs from the first
        refusal since the last resend: refusals of the frames in flight behind it keep coming, and restarting the
        clock at each put the resend off for as long as they did."""
        with self._cv:
            self.turned_away += 1
            self._refused_at = time.monotonic()  # the service answers: not a stall (_resend_loop)
            if seq is not None and seq in self._unanswered:
                self._refused.add(seq)
                if self._full is None:
                    self._full = self._refused_at

    def forget(self) -> None:
        """A new trajectory: the frames of the old one are not waited for."""
        with self._cv:
            self._unanswered.clear()
            self._refused.clear()
            self._full = None

    # -- the path's workers
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
                heard = max(self._last_answer, self._refused_at)  # frames a full queue turned away go by _full_due
                stalled = bool(self._unanswered) and not self._down and now - heard >= self.resend_after
                if not (back or stalled):
                    continue
                self._last_answer = now
            self.resend()  # frames in flight while it was away were lost; nothing new went out meanwhile
            if back:
                with self._cv:
                    self._down, self._back_at = False, None
                    self._cv.notify_all()

    def _full_due(self) -> bool:
        """Frames a full queue turned away sent again, in seq order, once a pose freed room (or after FULL_RETRY_S):
        FULL_BURST of them, the rest with the next pose (a queue takes a few frames and turns the rest away again:
        sending them all each time multiplied an overloaded worker's input). New frames wait until the last went."""
        with self._send_lock:
            with self._cv:
                at, now = self._full, time.monotonic()
                if at is None or (self._last_answer <= at and now - at < FULL_RETRY_S):
                    return False
                seqs = sorted(self._refused)[:FULL_BURST]
                self._refused.difference_update(seqs)
                self._full = now if self._refused else None
                pending = [self._unanswered[s] for s in seqs if s in self._unanswered]
                self._cv.notify_all()
            self._put_again(pending)
        return True

    def resend(self, first: int = 0, most: int | None = None) -> int:
        """Send the unanswered frames from seq `first` on again (the first `most` of them), in seq order; returns
        how many."""
        with self._send_lock:
            with self._cv:
                pending = sorted((seq, p) for seq, p in self._unanswered.items() if seq >= first)[:most]
                self._refused.difference_update(seq for seq, _ in pending)
            return self._put_again([p for _, p in pending])

    def _put_again(self, payloads: list[bytes]) -> int:
        """Copies of kept frames out, counted as resends; under _send_lock."""
        for payload in payloads:
            self._put(payload)
        self.resends += len(payloads)
        return len(payloads)

    # -- sending
    def send(self, seq: int, payload: bytes, timeout: float) -> None:
        """A new frame, kept until answered. While a worker of the path is away, or frames a full queue turned away
        wait to go again, it waits (at most `timeout`): it would overtake the lost ones, or be turned away too."""
        with self._cv:
            deadline = time.monotonic() + timeout
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

    def _put(self, payload: bytes) -> None:
        """A frame out, with the source info that names this client's session (services/limits.py); under _send_lock."""
        self._sn += 1
        self._pub.put(payload, source_info=zenoh.SourceInfo(self._pub.id, self._sn))

    def put_untracked(self, payload: bytes) -> None:
        """An encoded frame out as this client, not kept (tools and tests)."""
        with self._send_lock:
            self._put(payload)

    def close(self) -> None:
        self._closed.set()
        self._credit.set()
        self._resender.join(timeout=5)
        for s in self._subs:
            s.undeclare()
        self._pub.undeclare()
