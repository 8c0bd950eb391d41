"""What one client may cost a worker: streams admitted (per worker and per client), error events per client per
second, the length of keys and messages in logs and events. A refused stream gets one error event naming the limit.

Under `occvo serve` / `occvo up`'s logins (services/acl.py) and the shipped ACL (deploy/acl/), `client_identity:
"user"`: a client is a stream id's prefix before its first '.', which the access control ties to the login allowed to
publish under it. Otherwise (a worker's own default, the anonymous mode) `"session"`: the zid of the sample's source
info, which OccVOClient sets and the inference worker passes on with the occupancy frame; the publisher declares it
itself, so the identity is self-declared and the guards keyed on it advisory (a sample without one is "anonymous")."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

MAX_KEY_CHARS = 200  # a key in a log line or an error event (keys may be 60 kB of garbage)
MAX_MESSAGE_CHARS = 500


def clip(text: str, limit: int) -> str:
    """`text` cut to `limit` characters, saying how long it was."""
    text = str(text)
    return text if len(text) <= limit else f"{text[:limit]}...({len(text)} chars)"


def client_of(stream: str) -> str:
    return stream.split(".", 1)[0]


ANONYMOUS = "anonymous"


def identity_of(sample, stream: str, mode: str) -> str:
    """The client that published `sample` on `stream` (see the module's docstring)."""
    if mode == "user":
        return client_of(stream)
    info = sample.source_info
    return ANONYMOUS if info is None else str(info.source_id.zid)


class ErrorBudget:
    """A token bucket per client (Worker.report_error): `rate` events a second, bursts of `burst`. Suppressed events
    are counted and the next event that goes out says how many. Only the `streams` most recently reporting clients
    are remembered."""

    def __init__(self, rate: float, burst: int, streams: int = 4096):
        self.rate, self.burst, self.streams = rate, burst, streams
        self._lock = threading.Lock()
        self._buckets: OrderedDict[str, list] = OrderedDict()  # stream -> [tokens, last time, suppressed]

    def take(self, stream: str) -> int | None:
        """None: suppress this event; else the number suppressed since the last one that went out."""
        now = time.monotonic()
        with self._lock:
            b = self._buckets.pop(stream, None) or [float(self.burst), now, 0]
            self._buckets[stream] = b
            if len(self._buckets) > self.streams:
                self._buckets.popitem(last=False)
            b[0] = min(float(self.burst), b[0] + (now - b[1]) * self.rate)
            b[1] = now
            if b[0] < 1.0:
                b[2] += 1
                return None
            b[0] -= 1.0
            suppressed, b[2] = b[2], 0
            return suppressed


class Admission:
    """Which streams a worker serves: at most `max_streams`, at most `per_client` a client. A stream is bound to the
    client that it was admitted for (its owner) until it leaves: another client's frames for it are refused. Streams
    leave when their lane is retired (idle, or reclaimed for a new stream) so their places free up."""

    def __init__(self, max_streams: int, per_client: int):
        self.max_streams, self.per_client = max_streams, per_client
        self._lock = threading.Lock()
        self.owners: dict[str, str] = {}  # stream -> the client it was admitted for
        self.clients: dict[str, int] = {}
        self.leaving: set[str] = set()  # admitted streams whose lane is leaving: their places are taken

    @property
    def streams(self):
        return self.owners.keys()

    def admit(self, stream: str, client: str, reclaim=None) -> tuple[str, str] | None:
        """None if the stream is (now) admitted for `client`, else (error code, why not naming the limit).
        reclaim(candidates, idle_only) -> one of the (stream, rank) candidates whose lane is now on its way out
        (or None): tried before a new stream is refused (_reclaim)."""
        with self._lock:
            owner = self.owners.get(stream)
            if owner is not None:
                if owner == client:
                    return None
                return (
                    "not_owner",
                    f"frame for stream {stream!r} refused: the stream is bound to the client that opened it "
                    "until it is idle (idle_stream_s)",
                )
            if self.clients.get(client, 0) >= self.per_client and not self._reclaim(reclaim, client, True):
                return (
                    "stream_limit",
                    f"stream {stream!r} refused: client {client!r} has max_streams_per_client={self.per_client} "
                    "streams on this worker already",
                )
            if len(self.owners) - len(self.leaving) >= self.max_streams and not self._reclaim(reclaim, client, False):
                return (
                    "stream_limit",
                    f"stream {stream!r} refused: this worker serves max_streams={self.max_streams} streams already",
                )
            self.owners[stream] = client
            self.clients[client] = self.clients.get(client, 0) + 1
            return None

    def _reclaim(self, reclaim, client: str, own: bool) -> bool:
        """A place taken back for `client`: an idle stream of its own when `own`; else a stream of a client holding
        at least two streams more than it (the biggest first), idle or not, so that under contention every client
        keeps a fair share and none takes a place from one holding fewer than it."""
        if reclaim is None:
            return False
        staying: dict[str, int] = {}  # each client's streams not already on their way out
        for s, c in self.owners.items():
            if s not in self.leaving:
                staying[c] = staying.get(c, 0) + 1
        mine = staying.get(client, 0)
        if own:
            candidates = [(s, 0) for s, c in self.owners.items() if c == client and s not in self.leaving]
        else:
            candidates = [
                (s, -staying[c]) for s, c in self.owners.items() if s not in self.leaving and staying[c] > mine + 1
            ]
        got = reclaim(candidates, idle_only=own)
        if got is None:
            return False
        self.leaving.add(got)
        return True

    def leaves(self, stream: str) -> None:
        """An admitted stream whose lane has left (idle, or evicted for memory) and whose state is being given back:
        a new stream may take its place meanwhile (writing a big snapshot takes a while)."""
        with self._lock:
            if stream in self.owners:
                self.leaving.add(stream)

    def stays(self, stream: str) -> None:
        """A reclaimed stream whose lane got a frame before it left: it keeps its place."""
        with self._lock:
            self.leaving.discard(stream)

    def owner(self, stream: str) -> str | None:
        return self.owners.get(stream)

    def release(self, stream: str) -> None:
        with self._lock:
            self.leaving.discard(stream)
            client = self.owners.pop(stream, None)
            if client is not None:
                self.clients[client] -= 1
                if not self.clients[client]:
                    del self.clients[client]
