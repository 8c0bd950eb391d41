"""A worker's frames in, on Zenoh's callback: decoded once, admitted, charged to the memory cap and queued on their
stream's lane, or answered at once with the reason; never waited on. A stream whose queue is full under the lossless
policy gets `stream_full` for the frame (not an answer: the client sends it again), and its later frames get the same
until that one is in, so the stream's frames still enter in order and none is lost (services/client.py resends)."""

from __future__ import annotations

import functools
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

import zenoh

from occvo_schemas import keys
from occvo_services.lane_eviction import reclaim
from occvo_services.limits import identity_of

if TYPE_CHECKING:
    from occvo_services.runtime import Worker

MAX_TURNED_AWAY = 4096  # streams remembered with a frame turned away
RECENT = 256  # frames a stream remembers as entered
STALE_S = 3.0  # a turned-away frame not sent again this long is not waited for (OccVOClient resends within 1 s)


class TurnedAway:
    """Per stream, the frames a full queue turned away that have not entered its lane since (the frames after the
    first of them wait for it), and the frames that entered the lane since its last seq 0 (RECENT of them): a frame
    among those, turned away (a resend overlapping its original), is waited for by nothing, since its pose comes
    anyway. Every turned-away frame is remembered, not only the first: once the first is in, the next still missing
    holds the frames after it (an upstream worker may forward them before it). A wait no copy of its frame, nor of a
    frame waiting for it, renewed for STALE_S ends: the client has that frame's pose (a copy of it was turned away
    after a seq 0 copy came again), or it does not send again."""

    def __init__(self):
        self._lock = threading.Lock()
        self._away: dict[str, dict[int, float]] = {}  # stream -> {seq: when last turned away, or a copy after it came}
        self._in: dict[str, deque] = {}

    def waits(self, stream: str, seq: int) -> int | None:
        """The seq frame `seq` waits for, or None (seq 0 starts the stream again)."""
        with self._lock:
            away = self._away.get(stream)
            if away is None:
                return None
            entered, now = self._in.get(stream, ()), time.monotonic()
            if seq in away:  # a copy of a frame turned away: its client sends again, and so the frames it waits for
                for k in away:  # (their copies may be stopped upstream, out of this worker's sight)
                    if k < seq:
                        away[k] = now
            for k in [k for k, at in away.items() if seq == 0 or k in entered or now - at > STALE_S]:
                del away[k]  # a new trajectory, k is in after all, or nobody sends k again
            if not away:
                del self._away[stream]
                return None
            k = min(away)
            return None if seq <= k else k

    def turned_away(self, stream: str, seq: int) -> None:
        with self._lock:
            if seq != 0 and seq in self._in.get(stream, ()):
                return  # a copy of a frame in already: nothing waits for it
            away = self._away.get(stream)
            if away is None:
                away = self._away[stream] = {}
                _bound(self._away)
            away[seq] = time.monotonic()
            if len(away) > RECENT:  # stray seqs far ahead: the first ones are what the stream waits for
                del away[max(away)]

    def entered(self, stream: str, seq: int) -> None:
        with self._lock:
            entered = self._in.get(stream)
            if entered is None or seq == 0:
                entered = self._in[stream] = deque(maxlen=RECENT)
                _bound(self._in)
            entered.append(seq)
            away = self._away.get(stream)
            if away is not None:
                for k in [k for k in away if k <= seq or seq == 0]:
                    del away[k]
                if not away:
                    del self._away[stream]


def _bound(streams: dict) -> None:
    if len(streams) > MAX_TURNED_AWAY:  # the stream seen longest ago goes
        streams.pop(next(iter(streams)))


def enqueue(
    w: Worker, sample: zenoh.Sample, expect, handler: Callable[[str, object], None], judge_seq: bool, place
) -> None:
    """Decode a stream message, check its sequence number (judge_seq False: the handler does, against what it
    committed) and queue it on its stream's lane with its hop latency; bad messages are reported by decode_input
    and check_seq, never raised. place (services/registration/placing.py): the client's part of the admission
    judged here (a refused frame is never placed), the frame's owner decided off the callback, and the rest of its
    ingress after that; a frame another worker owns goes no further."""
    t_recv, t_decode = time.time(), time.perf_counter()
    client = identity_of(sample, keys.stream_of(str(sample.key_expr)), w.config.client_identity)
    msg = w.decode_input(sample, expect, client)
    if msg is None or w.stopping.is_set():
        return
    decode_ms = (time.perf_counter() - t_decode) * 1000.0
    w.stats.observe("decode", decode_ms)
    rest = functools.partial(_admit, w, sample, msg, handler, judge_seq, (t_recv, decode_ms))
    if place is None:
        return rest()
    if (refused := place.claim(msg.stream, client)) is not None:  # no store look-up, no lease row for it
        w.stats.inc("frames_refused_before_placement")
        if w.reports_input(msg.stream):  # every member refuses it: one reports
            code, why = refused
            seq = msg.seq if code == "stream_limit" else None  # not_owner: the owner's client would take it as its own
            w.report_error(msg.stream, code, why, str(sample.key_expr), seq, client=client)
        return
    if not place.submit(msg.stream, lambda: place.decide(msg) and rest()):
        _full(w, msg, f"seq {msg.seq} not placed: too many frames wait for their placement; send it again", "")


def _admit(w: Worker, sample: zenoh.Sample, msg, handler, judge_seq: bool, times: tuple) -> None:
    """After the decode (and the placement): admission, the sequence, the memory cap, the lane."""
    (t_recv, decode_ms), key = times, str(sample.key_expr)
    if not _admitted(w, msg, identity_of(sample, msg.stream, w.config.client_identity), key):
        return
    if judge_seq and not w.check_seq(msg.stream, msg.seq, key):
        w.release_unserved(msg.stream)  # admitted for nothing: its place goes back
        return
    if (waits_for := w.turned_away.waits(msg.stream, msg.seq)) is not None:
        why = f"seq {msg.seq} waits for seq {waits_for}, which its full queue turned away: send both again"
        return _full(w, msg, why, key)
    cost = _charged(w, msg, key)
    if cost is None:
        return
    # a sent_at a day off (e.g. 1e308) would give an infinite hop: no hop latency then, not a failed stage
    hop_ms = (t_recv - msg.sent_at) * 1000.0 if 0 < msg.sent_at and abs(t_recv - msg.sent_at) < 86400 else 0.0
    _queue(w, msg, (msg, hop_ms, time.perf_counter(), decode_ms, sample.source_info, cost), handler, key)


def _admitted(w: Worker, msg, client: str, key: str) -> bool:
    """The stream has (or gets) a place in the worker's admission and the frame comes from its client."""
    w.relieve_memory()
    refused = None
    if msg.stream not in w.admission.streams and (why := w.memory.refuse(msg.stream)) is not None:
        w.stats.inc("streams_refused_memory")
        refused = ("stream_limit", why)
    refused = refused or w.admission.admit(msg.stream, client, functools.partial(reclaim, w.lanes))
    if refused is None:
        return True
    code, why = refused
    w.stats.inc("streams_refused" if code == "stream_limit" else "frames_not_owner")
    # another client's frame: no seq in the event, the owner's client would take it for its own frame's answer
    w.report_error(msg.stream, code, why, key, msg.seq if code == "stream_limit" else None)
    return False


def _charged(w: Worker, msg, key: str) -> float | None:
    """The frame's cost charged to the memory cap (MB), or None: refused, and answered so."""
    cost, away = w.frame_cost_mb(msg), w.store_away()
    why = w.memory.charge(msg.stream, msg.seq, cost)
    if why is None:
        return cost
    w.stats.inc("frames_refused_memory")
    if not away and w.memory.fits_alone(cost):  # other frames in work hold the cap: this one waits its turn
        _full(w, msg, f"{why}; send it again when a pose comes", key)
        return None
    # the store away: the frames held for it fill the cap; this one is sent again once they are stored
    code, why = ("store_unavailable", f"{why}: frames held while {away}") if away else ("oversize", why)
    w.report_error(msg.stream, code, why, key, msg.seq)
    if away:
        w.not_held(msg.stream, msg.seq)
    return None


def _queue(w: Worker, msg, item: tuple, handler, key: str) -> None:
    """On the stream's lane, or answered: the store away and the queue full of held frames (store_unavailable), the
    queue full (stream_full). Nothing here waits."""
    cost, away = item[5], w.store_away()
    lane = w.lane(msg.stream, handler)
    try:
        if away and lane.queue.qsize() >= w.config.queue_size:  # held frames fill it: refused, not blocked
            w.memory.discharge(cost)
            w.stats.inc("frames_refused_store_away")
            why = f"seq {msg.seq} not held: {w.config.queue_size} frames of the stream wait for the store ({away})"
            w.report_error(msg.stream, "store_unavailable", why, key, msg.seq)
            w.not_held(msg.stream, msg.seq)
            return
        if lane.put(item):
            w.turned_away.entered(msg.stream, msg.seq)
            return
        w.memory.discharge(cost)
        if not w.stopping.is_set():
            why = f"seq {msg.seq} not queued: {w.config.queue_size} frames of the stream wait; send it again"
            _full(w, msg, why, key)
    finally:
        w.lane_entered(lane)


def _full(w: Worker, msg, why: str, key: str) -> None:
    """Lossless and the stream's queue full: the frame and those after it are turned away until it is in."""
    w.turned_away.turned_away(msg.stream, msg.seq)
    w.stats.inc("frames_refused_full")
    w.report_error(msg.stream, "stream_full", why, key or keys.occupancy(msg.stream), msg.seq)
