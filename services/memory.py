"""A worker's memory cap (`max_rss_mb`): new streams are refused and idle streams evicted as its resident set nears
the cap, so a flood of streams cannot grow a worker until the machine swaps or the OOM killer picks a process.

Admission is the lever because a worker's memory is its streams' (a one-frame registration stream holds 10-25 MB; a
long drive's working map hundreds). Two marks below the cap: over EVICT_SHARE of it, the stream idle longest (no
frame for EVICT_IDLE_S) gives back its lane and state, as an idle stream does after idle_stream_s (with a store its
OccVO is snapshotted and dropped; the next frame resumes it); over ADMIT_SHARE, a new stream is refused with an error
event naming the cap. Streams already admitted keep running: the rest of the cap is their headroom."""

from __future__ import annotations

import os
import threading
import time

ADMIT_SHARE = 0.85  # new streams refused above this share of the cap
EVICT_SHARE = 0.75  # idle streams evicted above it
EVICT_IDLE_S = 1.0  # a lane without a frame this long may be evicted (a live stream at >= 1 frame/s never is)
CHECK_EVERY_S = 0.1  # between two reads of the resident set (a read is a /proc file)

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_mb() -> float:
    """This process's resident set in MB (0 where /proc is missing: no cap is enforced then)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE / (1 << 20)
    except (OSError, ValueError, IndexError):
        return 0.0


class MemoryCap:
    """The resident set against `max_rss_mb` (None: no cap), read at most every CHECK_EVERY_S."""

    def __init__(self, max_rss_mb: int | None):
        self.max_rss_mb = max_rss_mb
        self._lock = threading.Lock()
        self._read_at = -1.0
        self._rss = 0.0
        self.charged = 0.0  # MB the frames queued and in work will cost, charged before they are queued

    def rss(self) -> float:
        now = time.monotonic()
        with self._lock:
            if now - self._read_at >= CHECK_EVERY_S:
                self._rss, self._read_at = rss_mb(), now
            return self._rss

    def refuse(self, stream: str) -> str | None:
        """Why a new stream is refused now, naming the cap; None to admit it."""
        if self.max_rss_mb is None:
            return None
        rss = self.rss()
        if rss < ADMIT_SHARE * self.max_rss_mb:
            return None
        return (
            f"stream {stream!r} refused: this worker's memory is {rss:.0f} MB, over {ADMIT_SHARE:.0%} of "
            f"max_rss_mb={self.max_rss_mb} (streams already served keep the rest)"
        )

    def over_evict_mark(self) -> bool:
        return self.max_rss_mb is not None and self.rss() >= EVICT_SHARE * self.max_rss_mb

    def charge(self, stream: str, seq: int, mb: float) -> str | None:
        """Charge a frame's cost (MB) before it is queued; why it is refused (naming the cap), or None. A refused
        frame would take the resident set with the frames already charged past max_rss_mb."""
        if self.max_rss_mb is None or mb <= 0:
            return None
        rss = self.rss()
        with self._lock:
            if rss + self.charged + mb <= self.max_rss_mb:
                self.charged += mb
                return None
            charged = self.charged
        return (
            f"seq {seq} of stream {stream!r} refused: it would cost about {mb:.0f} MB, and this worker's "
            f"{rss:.0f} MB with {charged:.0f} MB of frames in work would pass max_rss_mb={self.max_rss_mb}"
        )

    def fits_alone(self, mb: float) -> bool:
        """Whether a frame refused by `charge` would fit once the frames now in work are done: the refusal is then
        a matter of waiting (the client sends it again), not of the frame's size."""
        return self.max_rss_mb is None or self.rss() + mb <= self.max_rss_mb

    def discharge(self, mb: float) -> None:
        """A charged frame is done (or dropped)."""
        if mb > 0:
            with self._lock:
                self.charged = max(0.0, self.charged - mb)
