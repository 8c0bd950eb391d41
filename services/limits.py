"""What one client may cost a worker: streams admitted (per worker and per client), error events per stream per
second, the length of keys and messages in logs and events. A refused stream gets one error event naming the limit.

Zenoh does not tell a subscriber who published a sample, so a "client" is a stream id's prefix before its first '.'
(`cam1.front` is client `cam1`'s); the shipped ACL (deploy/acl/) lets each user publish only under its own prefix,
which makes the prefix the publisher."""

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


class ErrorBudget:
    """A token bucket per stream: `rate` events a second, bursts of `burst`. Suppressed events are counted and the
    next event that goes out says how many. Only the `streams` most recently reporting streams are remembered."""

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
    """Which streams a worker serves: at most `max_streams`, at most `per_client` a client. Streams leave when their
    lane is retired (idle) so their places free up."""

    def __init__(self, max_streams: int, per_client: int):
        self.max_streams, self.per_client = max_streams, per_client
        self._lock = threading.Lock()
        self.streams: set[str] = set()
        self.clients: dict[str, int] = {}

    def admit(self, stream: str) -> str | None:
        """None if the stream is (now) admitted, else why not, naming the limit."""
        with self._lock:
            if stream in self.streams:
                return None
            if len(self.streams) >= self.max_streams:
                return f"stream {stream!r} refused: this worker serves max_streams={self.max_streams} streams already"
            client = client_of(stream)
            if self.clients.get(client, 0) >= self.per_client:
                return (
                    f"stream {stream!r} refused: client {client!r} has max_streams_per_client={self.per_client} "
                    "streams on this worker already"
                )
            self.streams.add(stream)
            self.clients[client] = self.clients.get(client, 0) + 1
            return None

    def release(self, stream: str) -> None:
        with self._lock:
            if stream in self.streams:
                self.streams.discard(stream)
                client = client_of(stream)
                self.clients[client] -= 1
                if not self.clients[client]:
                    del self.clients[client]
