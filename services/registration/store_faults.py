"""Store faults, as the registration worker meets them. A write refused (disk full: `not_stored`; fenced: another
worker owns the stream now) or the store away. The store away is StoreOutage: from the first call that could not reach the database until
a probe reaches it again. Meanwhile a frame that reaches a stream's lane waits there for the store (its lane's
frames queue behind it, within the worker's memory cap and the lane's queue); a frame that cannot be held, or whose
write failed, is answered `store_unavailable`, which is not an answer: the client sends it again until it is stored.
Once the store is back every stream resumes from what it stored, so no accepted frame is lost whatever the outage's
length."""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

from occvo_services.store.errors import FencedError, StoreUnavailable
from occvo_services.store.url import redact
from occvo_services.telemetry import log_event

if TYPE_CHECKING:
    from occvo_services.registration.pose_path import PosePath

PROBE_EVERY_S = 0.5  # between two tries to reach the store while it is away
MAX_UNSTORED = 1024  # frames a stream remembers as refused or turned away


class StoreOutage:
    def __init__(self, store, stopping: threading.Event, stats, log: logging.Logger):
        self.store, self.stopping, self.stats, self.log = store, stopping, stats, log
        self._lock = threading.Lock()  # one waiting lane probes at a time; the others find the answer
        self._down_since: float | None = None
        self.why = ""

    @property
    def down(self) -> bool:
        return self._down_since is not None

    def saw(self, exc: BaseException) -> bool:
        """Whether `exc` says the store is away (then the outage starts, if it had not)."""
        if not isinstance(exc, StoreUnavailable):
            return False
        with self._lock:
            if self._down_since is None:
                self._down_since, self.why = time.monotonic(), redact(str(exc))
                self.stats.inc("store_outages")
                log_event(self.log, "store unavailable: frames held or answered store_unavailable", logging.WARNING,
                          error=self.why)  # fmt: skip
        return True

    def wait_back(self) -> bool:
        """Block until the store answers again (True), or the worker stops (False)."""
        while self.down:
            with self._lock:
                if self._down_since is not None and self._probe():
                    took = time.monotonic() - self._down_since
                    self._down_since = None
                    log_event(self.log, "store back: held frames go on", seconds_away=round(took, 1))
                    return True
            if self.stopping.wait(PROBE_EVERY_S):
                return False
        return True

    def _probe(self) -> bool:
        try:
            self.store.ping()
        except StoreUnavailable:
            return False
        return True


# -- a session's part ---------------------------------------------------------------------------------------------------
def store_back(s: PosePath, seq: int) -> bool:
    """The store away: the frame waits for it in its lane (the lane's next frames queue behind it). False if the
    worker stops first: the frame is answered store_unavailable (the client sends it again)."""
    outage = s.ctx.outage
    if outage is None or not outage.down or outage.wait_back():
        return True
    s.report("store_unavailable", f"seq {seq} not registered: {outage.why}; send it again", seq)
    return False


def store_failed(s: PosePath, seq: int, exc: Exception, what: str) -> None:
    """A write or read failed (disk full, the database away, or fenced: another worker owns the stream now): drop
    the in-memory state; the stream resumes from the store at its next frame (replaying the journal redoes what was
    not stored), after taking the lease again if it was fenced."""
    fenced = isinstance(exc, FencedError)
    s.drop_state(fenced)  # the tiles too are started again by the resume
    if fenced:  # the new owner has this frame too: not this worker's to answer
        s.ctx.leases.placement.forget(s.stream)
        s.ctx.stats.inc("fenced")
        log_event(
            s.ctx.log, "fenced: the stream has another owner", logging.WARNING, stream=s.stream, seq=seq, error=str(exc)
        )
        return
    message = f"seq {seq} {what} ({type(exc).__name__}: {exc}); the stream resumes from the store at its next frame"
    away = s.ctx.outage is not None and s.ctx.outage.saw(exc)
    s.report("store_unavailable" if away else "not_stored", message, seq)  # not answers: the client resends


class Refusals:
    """The frames of a stream the store refused or that were turned away: the frames after the first of them wait
    for it. Marked by the stream's lane and by the worker's frame callback (a frame not held while the store is
    away), hence the lock."""

    def __init__(self, report):
        self._report = report  # (code, message, seq): the stream's error event
        self._lock = threading.Lock()
        self._seqs: set[int] = set()

    def refused(self, k: int) -> None:
        """Frame k was not stored (or not held while the store was away): the frames after it wait for it
        (waits). Registered without it, its pose would be missing for good: the frame after a gap confirms a held
        jump."""
        with self._lock:
            self._mark(k)

    def _mark(self, seq: int) -> None:
        self._seqs.add(seq)
        if len(self._seqs) > MAX_UNSTORED:  # stray seqs far ahead: the first ones are what the stream waits for
            self._seqs.discard(max(self._seqs))

    def waits(self, seq: int) -> bool:
        """After the store refused seq k (disk full, the database away), the frames after k wait for k, which the
        client sends again with them in order. A frame turned away so waits in turn: once k is registered, the first
        of them is the next to come (before, k+2 coming before the turned-away k+1 was held as a jump, which k+3
        confirmed, and k+1's pose was missing for good)."""
        with self._lock:
            if seq == 0:
                self._seqs.clear()
                return False
            k = min(self._seqs, default=None)
            if k is None or seq <= k:
                self._seqs.discard(seq)
                return False
            self._mark(seq)
        self._report("not_stored", f"seq {seq} waits for seq {k}, which the store refused: send both again", seq)
        return True
