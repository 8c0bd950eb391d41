"""Placement "members": the client's part of the admission, judged before a frame's placement. Every member decodes
every frame, so each sees the same streams and clients; a frame its client may not send (a stream bound to another
client, a new stream beyond the client's share) is refused here, before any store look-up or lease row. The owner's
part (its stream slots, its memory) is judged after the placement (services/ingress.py)."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from occvo_services.memory import EVICT_IDLE_S

MAX_CLAIMS = 4096  # streams remembered (ids are the clients' to invent); one forgotten is judged again by its owner


class Claims:
    """Which client holds each stream (the client of its first frame, while its frames keep coming), and at most
    `per_client` streams a client on each live member (`members()`). A client's stream without a frame for
    EVICT_IDLE_S gives its claim to the client's next new stream, as the owner's admission reclaims its lane."""

    def __init__(self, per_client: int, idle_s: float, members: Callable[[], int]):
        self.per_client, self.idle_s, self.members = per_client, idle_s, members
        self._lock = threading.Lock()
        self._streams: OrderedDict[str, list] = OrderedDict()  # stream -> [client, last frame], oldest first
        self._clients: dict[str, set[str]] = {}

    def claim(self, stream: str, client: str) -> tuple[str, str] | None:
        """None if `client` may send this frame of `stream` (claimed for it now), else (error code, why)."""
        now = time.monotonic()
        with self._lock:
            self._expire(now)
            held = self._streams.get(stream)
            if held is not None:
                if held[0] != client:
                    return "not_owner", (
                        f"frame for stream {stream!r} refused: the stream is bound to the client that opened it "
                        "until it is idle (idle_stream_s)"
                    )
                held[1] = now
                self._streams.move_to_end(stream)
                return None
            share = self.per_client * max(1, self.members())
            mine = self._clients.get(client, set())
            if len(mine) >= share and not self._give_back_idle(mine, now):
                return "stream_limit", (
                    f"stream {stream!r} refused: client {client!r} has max_streams_per_client={self.per_client} "
                    f"streams on each of the {share // self.per_client} registration workers already"
                )
            self._streams[stream] = [client, now]
            self._clients.setdefault(client, set()).add(stream)
            if len(self._streams) > MAX_CLAIMS:
                self._drop(next(iter(self._streams)))
            return None

    def _give_back_idle(self, mine: set[str], now: float) -> bool:
        """The client's stream idle longest (at least EVICT_IDLE_S) gives back its claim."""
        idle = [s for s in mine if now - self._streams[s][1] >= EVICT_IDLE_S]
        if not idle:
            return False
        self._drop(min(idle, key=lambda s: self._streams[s][1]))
        return True

    def _expire(self, now: float) -> None:
        while self._streams:
            stream, (_, last) = next(iter(self._streams.items()))
            if now - last < self.idle_s:
                return
            self._drop(stream)

    def _drop(self, stream: str) -> None:
        client, _ = self._streams.pop(stream)
        mine = self._clients[client]
        mine.discard(stream)
        if not mine:
            del self._clients[client]
