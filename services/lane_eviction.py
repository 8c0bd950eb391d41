"""Which of a worker's lanes is given back before its idle time: one idle lane told to leave so that a new stream
takes its place (the admission's reclaim), and the lane idle longest as the resident set nears max_rss_mb
(services/memory.py, Worker.relieve_memory). Each lane is told by its own method (StreamLane.evict)."""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

from occvo_services.memory import EVICT_IDLE_S

if TYPE_CHECKING:
    from occvo_services.flow import StreamLane


def reclaim(lanes: Mapping[str, StreamLane], candidates: list[tuple[str, int]], idle_only: bool) -> str | None:
    """Of the (stream, rank) candidates, the lowest rank's lane without a frame for longest (idle_only: for
    EVICT_IDLE_S at least) and none in work or waiting: told to leave, its stream returned (a new stream takes
    its place), else None. Reads the lanes without their lock (the admission's is held); retire_lane checks
    again under it."""
    now, ready = time.monotonic(), []
    for stream, rank in candidates:
        lane = lanes.get(stream)
        if lane is None or lane.busy or lane.pending or lane.evicting or lane.queue.qsize():
            continue
        if idle_only and now - lane.last_active < EVICT_IDLE_S:
            continue
        ready.append((rank, lane.last_active, stream))
    for _, _, stream in sorted(ready):
        if lanes[stream].evict("reclaimed"):
            return stream
    return None


def longest_idle(lanes: Iterable[StreamLane], now: float) -> StreamLane | None:
    """The lane idle longest (EVICT_IDLE_S at least, nothing queued or in work), the one memory pressure evicts;
    None while another is on its way out (the resident set is read again before the next is chosen)."""
    lanes = list(lanes)
    if any(lane.evicting for lane in lanes):
        return None
    idle = [
        lane
        for lane in lanes
        if not lane.busy and not lane.pending and not lane.queue.qsize() and now - lane.last_active >= EVICT_IDLE_S
    ]
    return min(idle, key=lambda lane: lane.last_active) if idle else None
