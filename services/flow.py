"""Flow of frames through a worker: bounded stage queues, per-stream sequence checks and the stream lane (one queue
a stream and its strand on the worker's lane pool, in arrival order)."""

from __future__ import annotations

import bisect
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from occvo_schemas.codec import CodecError
from occvo_services.strand import Strand
from occvo_services.telemetry import log_event
from occvo_services.worker_config import Policy

if TYPE_CHECKING:
    from occvo_services.runtime import Worker


class StageQueue:
    """Bounded queue between two stages; put never waits. lossless: a full queue refuses the item (its sender is
    answered, and sends it again); latest: the oldest item is dropped."""

    def __init__(self, maxsize: int, policy: Policy, on_drop: Callable[[object], None], stop: threading.Event):
        self.q: queue.Queue = queue.Queue(maxsize=maxsize)
        self.policy = policy
        self.on_drop = on_drop
        self.stop = stop

    def put(self, item) -> bool:
        """False when the item was not queued: the worker is stopping, or (lossless) the queue is full."""
        if self.stop.is_set():
            return False
        if self.policy == "lossless":
            try:
                self.q.put_nowait(item)
                return True
            except queue.Full:
                return False
        while True:
            try:
                self.q.put_nowait(item)
                return True
            except queue.Full:
                try:
                    self.on_drop(self.q.get_nowait())
                except queue.Empty:
                    continue  # a consumer took the oldest meanwhile: there is room now, put again

    def get(self, timeout: float):
        return self.q.get(timeout=timeout)

    def qsize(self) -> int:
        return self.q.qsize()


def judge_seq(seq: int, last: int | None, max_jump: int | None, older: str = "") -> tuple[bool, str | None, str | None]:
    """Every worker's sequence rule: (accept, error code, message) of frame `seq` after frame `last` (None: nothing
    before it). seq 0 starts a new trajectory; a gap is reported as missing and accepted; a step back is out of order
    (`older` says more of it); a step forward of more than max_jump is reported and not adopted: one stray seq must not
    make every following real frame a step back."""
    if last is None or seq == 0 or seq == last + 1:
        return True, None, None
    if max_jump is not None and seq - last > max_jump:
        return (
            False,
            "seq_jump",
            f"seq {seq} is {seq - last} after seq {last}, beyond the window of {max_jump}; dropped",
        )
    if seq > last + 1:
        return True, "missing_seq", f"missing seq {last + 1}..{seq - 1} ({seq - last - 1} frames) before seq {seq}"
    return False, "out_of_order", f"seq {seq} arrived after seq {last}{older}; dropped"


class SeqTracker:
    """Per-stream sequence check of a worker that keeps no trajectory (judge_seq against the last accepted seq). A
    jump (a gap) is passed on but not adopted until the frame after it comes: a stray seq within max_jump must not
    make the stream's real next frames steps back (the registration worker holds the jump until then)."""

    def __init__(self, max_jump: int | None = None):
        self.expected: int | None = None
        self.held: int | None = None  # the last jump passed on and not yet confirmed
        self.max_jump = max_jump

    def check(self, seq: int) -> tuple[bool, str | None, str | None]:
        """(accept, error code, message); an accepted seq (a jump once confirmed) is the one the next is judged
        against."""
        if self.held is not None and seq == self.held + 1 and self.expected is not None and seq > self.expected:
            self.held, self.expected = None, seq + 1  # the jump confirmed
            return True, None, None
        verdict = judge_seq(seq, None if self.expected is None else self.expected - 1, self.max_jump)
        if verdict[0]:
            if verdict[1] == "missing_seq":
                self.held = seq
            else:
                self.held, self.expected = None, seq + 1
        return verdict


class SeqRanges:
    """A set of seqs kept as sorted, disjoint runs [lo, hi]: a stream's frames are mostly consecutive, so a whole
    trajectory is a few runs; the lowest runs go first past `most`."""

    def __init__(self, most: int = 256):
        self.lo: list[int] = []
        self.hi: list[int] = []
        self.most = most

    def add(self, seq: int) -> None:
        lo, hi = self.lo, self.hi
        if hi and hi[-1] + 1 == seq:  # the next frame: the usual case
            hi[-1] = seq
            return
        i = bisect.bisect_right(lo, seq)
        if i and hi[i - 1] >= seq:
            return  # in already
        after = i < len(lo) and lo[i] == seq + 1
        if i and hi[i - 1] + 1 == seq:
            hi[i - 1] = hi.pop(i) if after else seq
            if after:
                lo.pop(i)
        elif after:
            lo[i] = seq
        else:
            lo.insert(i, seq)
            hi.insert(i, seq)
            if len(lo) > self.most:
                del lo[0], hi[0]

    def __contains__(self, seq: int) -> bool:
        i = bisect.bisect_right(self.lo, seq)
        return bool(i) and self.hi[i - 1] >= seq


EVICT = object()  # put on an idle lane's queue: the lane ends and its stream's state is given back (services/memory.py)
LANE_THREADS = 8  # a worker's lane pool: frames of this many streams handled at once, whatever the streams


class StreamLane:
    """One stream's bounded queue and its strand on the worker's lane pool (services/strand.py): the stage runs on
    the stream's frames one at a time, in arrival (= sequence) order, with no thread of the stream's own."""

    def __init__(
        self, worker: Worker, stream: str, handler: Callable[[str, object], None], after: StreamLane | None = None
    ):
        self.worker, self.stream, self.handler = worker, stream, handler
        self.busy = False
        self.evicting = False  # EVICT is on its way to this lane
        self.evict_why = "memory"  # or "reclaimed": its place goes to a new stream
        self.retiring = False  # idle_stream_s without a frame: its retirement is queued on its strand
        self.last_active = time.monotonic()  # the end of its last frame (the stream idle longest is evicted first)
        self.pending = 0  # frames handed to this lane, not yet in its queue (handed, entered: under Worker._lanes_lock)
        self.ended = threading.Event()  # retired: its stream's state given back
        self.queue = StageQueue(worker.config.queue_size, worker.config.policy, self._dropped, worker.stopping)
        self.strand = Strand(worker.lane_pool)
        if after is not None:  # the stream's retired lane, still giving back its state: this one starts when it is done
            self.strand.submit(after.ended.wait)

    def put(self, item) -> bool:
        """A frame queued and its turn taken on the strand; False if not queued (stopping, or lossless and full)."""
        if not self.queue.put(item):
            return False
        self.strand.submit(self._take)
        return True

    def post(self, item) -> bool:
        """An item queued without waiting (EVICT); False if the queue is full."""
        try:
            self.queue.q.put_nowait(item)
        except queue.Full:
            return False
        self.strand.submit(self._take)
        return True

    def evict(self, why: str) -> bool:
        """EVICT queued without waiting, `why` ("memory", "reclaimed") kept for its turn; False if the queue is full.
        Marked before it is queued: its turn may come on a pool thread before post() returns."""
        self.evicting, self.evict_why = True, why
        if not self.post(EVICT):
            self.evicting = False
            return False
        return True

    def handed(self) -> None:
        """A frame is on its way to this lane (Worker.lane; under the worker's _lanes_lock)."""
        self.pending += 1

    def entered(self) -> None:
        """A frame handed to this lane is queued or answered (Worker.lane_entered; under the worker's _lanes_lock)."""
        self.pending -= 1

    def idle_for(self, now: float) -> float:
        """Seconds since its last frame ended, 0 while a frame is queued, on its way or in work."""
        if self.busy or self.pending or self.queue.qsize() or not self.strand.idle:
            return 0.0
        return now - self.last_active

    def retire_when_idle(self) -> None:
        """idle_stream_s without a frame: the lane leaves, unless one comes before its turn."""
        if not self.retiring:
            self.retiring = True
            self.strand.submit(self._retire, "idle")

    def _retire(self, why: str) -> bool:
        self.retiring = False
        if self.worker.retire_lane(self, why):
            self.ended.set()
            return True
        return False

    def _dropped(self, item) -> None:
        self._done(item)
        self.worker.stats.inc("drops")
        log_event(self.worker.log, "dropped oldest frame", logging.DEBUG, stream=self.stream)

    def _take(self) -> None:
        """The next item of the queue, on a thread of the lane pool (the frame in hand is finished, even when
        stopping; after a stop nothing more is taken)."""
        if self.worker.stopping.is_set() or self.ended.is_set():
            return
        try:
            item = self.queue.q.get_nowait()
        except queue.Empty:  # the latest policy dropped it
            return
        if item is EVICT:
            self.evicting = False
            if not self._retire(self.evict_why):
                self.worker.admission.stays(self.stream)  # a frame came meanwhile: it keeps its place
            return
        if item is not None:
            self._handle(item)

    def _handle(self, item) -> None:
        self.busy = True
        try:
            self.handler(self.stream, item)
        except Exception as exc:  # noqa: BLE001 - a worker never dies of one frame
            seq = getattr(item[0], "seq", None) if isinstance(item, tuple) and item else None
            if isinstance(exc, CodecError):  # e.g. an output over the size limit: the frame's problem, named so
                self.worker.report_error(self.stream, exc.code, f"seq {seq}: output not sent: {exc.message}", seq=seq)
            else:
                self.worker.report_error(self.stream, "internal", f"{type(exc).__name__}: {exc}", seq=seq)
            log_event(self.worker.log, "stage failed", logging.ERROR, stream=self.stream, error=repr(exc))
        finally:
            self._done(item)
            self.busy = False
            self.last_active = time.monotonic()

    def _done(self, item) -> None:
        """A frame handled or dropped: its memory charge (Worker.enqueue) is given back."""
        if isinstance(item, tuple) and len(item) > 5:
            self.worker.memory.discharge(item[5])
