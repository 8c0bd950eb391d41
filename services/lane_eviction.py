"""A worker's lanes given back before their idle time: one idle lane told to leave so that a new stream takes its
place (the admission's reclaim), and the lane idle longest evicted as the resident set nears max_rss_mb
(services/memory.py)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from occvo_services.flow import EVICT
from occvo_services.memory import CHECK_EVERY_S, EVICT_IDLE_S

if TYPE_CHECKING:
    from occvo_services.runtime import Worker


def reclaim(w: Worker, candidates: list[tuple[str, int]], idle_only: bool) -> str | None:
    """Of the (stream, rank) candidates, the lowest rank's lane without a frame for longest (idle_only: for
    EVICT_IDLE_S at least) and none in work or waiting: told to leave, its stream returned (a new stream takes
    its place), else None. Reads the lanes without their lock (the admission's is held); retire_lane checks
    again under it."""
    now, lanes, ready = time.monotonic(), w.lanes, []
    for stream, rank in candidates:
        lane = lanes.get(stream)
        if lane is None or lane.busy or lane.pending or lane.evicting or lane.queue.qsize():
            continue
        if idle_only and now - lane.last_active < EVICT_IDLE_S:
            continue
        ready.append((rank, lane.last_active, stream))
    for _, _, stream in sorted(ready):
        lane = lanes[stream]
        if not lane.post(EVICT):
            continue
        lane.evicting, lane.evict_why = True, "reclaimed"
        return stream
    return None


def relieve_memory(w: Worker) -> None:
    """Over the eviction mark of max_rss_mb: the lane idle longest ends (one at a time, and the resident set is
    read again before the next is chosen)."""
    now = time.monotonic()
    if now - w._evicted_at < CHECK_EVERY_S or not w.memory.over_evict_mark():
        return
    with w._lanes_lock:
        if any(lane.evicting for lane in w.lanes.values()):
            return
        idle = [
            lane
            for lane in w.lanes.values()
            if not lane.busy and not lane.pending and not lane.queue.qsize() and now - lane.last_active >= EVICT_IDLE_S
        ]
        if not idle:
            return
        lane = min(idle, key=lambda lane: lane.last_active)
        if not lane.post(EVICT):
            return
        lane.evicting, lane.evict_why, w._evicted_at = True, "memory", now
