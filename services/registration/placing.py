"""Placement "members" off Zenoh's callback: whether this worker owns a decoded frame's stream may ask the store (a
stream not seen before, an owner gone), so the decision and the rest of the frame's ingress run on a small pool. The
frames of one stream keep their order: a stream always goes to the same one of a few strands (services/strand.py).
Only a frame its client may send is placed: the client's part of the admission (claim, services/registration/
claims.py) is judged on the callback first, so a refused frame costs no store look-up and no lease row."""

from __future__ import annotations

import threading
import zlib
from collections.abc import Callable

from occvo_services.strand import Strand, pool

STRANDS = 16  # a stream's frames go to strand crc32(stream) % STRANDS: a slow store call holds up only its share
MAX_WAITING = 64  # frames a strand holds for their placement; more are turned away (stream_full)


class Placing:
    """The frames waiting for their placement, and the decision (decide(msg) -> this worker owns its stream); before
    it, claim(stream, client) -> None, or the (code, why) its client's frame is refused with."""

    def __init__(self, decide: Callable[[object], bool], claim: Callable[[str, str], tuple | None], threads: int = 2):
        self.decide, self.claim = decide, claim
        self._pool = pool(threads, "placement")
        self._strands = [Strand(self._pool) for _ in range(STRANDS)]
        self._waiting = [0] * STRANDS
        self._lock = threading.Lock()

    def submit(self, stream: str, fn: Callable[[], None]) -> bool:
        """fn() after the stream's frames before it; False (nothing queued) if its strand holds MAX_WAITING."""
        i = zlib.crc32(stream.encode()) % STRANDS
        with self._lock:
            if self._waiting[i] >= MAX_WAITING:
                return False
            self._waiting[i] += 1
        self._strands[i].submit(self._run, i, fn)
        return True

    def _run(self, i: int, fn: Callable[[], None]) -> None:
        try:
            fn()
        finally:
            with self._lock:
                self._waiting[i] -= 1

    def close(self) -> None:
        self._pool.shutdown(wait=False)
