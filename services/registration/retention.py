"""What a client may keep in the store, and for how long (the registration worker, with a store).

Quotas per client (client_identity, services/limits.py): at most max_stored_streams_per_client streams and
max_store_mb_per_client MB. A client's bytes are what the store records of its streams (services/store_retention.py)
with their share of the store's own pages, plus, for its streams live on this worker, their state beyond their last
snapshot (a stream's snapshot is most of what it stores, written when it goes idle). A new stream needs room for one
as big as the client's biggest (stored, or live here), so the quota holds after it too. Over a quota, the client's
frames that would grow the store are refused with one error event, code store_quota, naming the quota; what is
stored stays. With a stream TTL the client's streams idle past it are deleted first, then the quota is checked again.

Stream TTL (stream_ttl_s): a stored stream without a frame for that long is deleted, as `occvo store delete` does
(trajectory, journal, snapshot, cold tiles, lease, and its map tiles where the map service shares the store). Only
by the worker that would serve it, and never while it has a live session there (a lane, or one being retired)."""

from __future__ import annotations

import logging
import threading
import time

from occvo_services.limits import ANONYMOUS
from occvo_services.registration.snapshots import state_bytes
from occvo_services.telemetry import log_event


class Retention:
    def __init__(self, worker):
        self.w, c = worker, worker.config
        self.quota_bytes = None if c.max_store_mb_per_client is None else c.max_store_mb_per_client << 20
        self.quota_streams = c.max_stored_streams_per_client
        self.ttl_s = c.stream_ttl_s
        self._maps = None  # the map store, where the map service's tables are in this store (at the first deletion)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self.ttl_s is not None:
            self._thread = threading.Thread(target=self._sweep_loop, name="stream-ttl", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._maps is not None:
            self._maps.close()

    # -- quotas
    def refuse(self, stream: str, client: str | None, seq: int) -> str | None:
        """Why frame `seq` of `stream` is refused for its client's quota, or None. A frame the stream has committed
        already (a resend, answered with its stored pose) grows nothing."""
        if self.quota_bytes is None and self.quota_streams is None:
            return None
        session = self.w.sessions.get(stream)
        view = None if session is None else session.view
        if view is not None and view.has(seq):
            return None
        client = client or ANONYMOUS
        try:
            why = self._over(stream, client, seq)
            if why is not None and self.ttl_s is not None and self.expire(client):
                why = self._over(stream, client, seq)
        except Exception as exc:  # noqa: BLE001 - the store away: its commit fails and names it (not_stored)
            log_event(self.w.log, "store quota not checked", logging.WARNING, stream=stream, error=repr(exc))
            return None
        return why

    def _over(self, stream: str, client: str, seq: int) -> str | None:
        """A new stream of the client needs room for one as big as its biggest stored; a frame of a stream it has
        needs the quota not reached."""
        store = self.w.store
        held = store.stream_usage(stream)
        new = held is None or held[0] != client
        if new and self.quota_bytes is not None:
            self._settle(client, stream)
        streams, used, biggest = store.usage_of(client)
        share = store.overhead()  # the store's own pages, in proportion
        used, biggest = int(used * share), int(biggest * share)
        if new and self.quota_streams is not None and streams >= self.quota_streams:
            return (
                f"stream {stream!r} not stored: client {client!r} has {streams} streams in the store, "
                f"max_stored_streams_per_client={self.quota_streams} (store_quota; `occvo store delete` frees them)"
            )
        if self.quota_bytes is not None:
            unsaved, live_biggest = self._unsaved(client)
            used, biggest = used + unsaved, max(biggest, live_biggest)
            if used + (biggest if new else 0) >= self.quota_bytes:
                return (
                    f"seq {seq} of stream {stream!r} not stored: client {client!r} has {used / 2**20:.0f} MB in the "
                    f"store, max_store_mb_per_client={self.quota_bytes >> 20}"
                    + (f" and its streams take up to {biggest / 2**20:.1f} MB" if new else "")
                    + " (store_quota; `occvo store delete` frees it)"
                )
        return None

    def _settle(self, client: str, new: str) -> None:
        """Before a new stream of the client is judged: the work after its other live streams' poses (which fills
        their maps and sends their tiles) done and their bytes measured, so a client opening stream after stream is
        counted in full (only its own streams wait)."""
        for stream, s in self.w.sessions_now():
            if stream != new and s.vo is not None and self.w.admission.owner(stream) == client:
                s.threads.settle()
                self.w.store.measure(stream)

    def _unsaved(self, client: str) -> tuple[int, int]:
        """What the snapshots of the client's live streams on this worker will add: their state beyond the one last
        written (a stream's snapshot is most of what it stores, written when it goes idle); and the biggest state."""
        total = biggest = 0
        for stream, s in self.w.sessions_now():
            vo = s.vo
            if vo is None or self.w.admission.owner(stream) != client:
                continue
            try:
                live = state_bytes(vo.state_dict(copy=False))  # views: nothing copied
            except RuntimeError:  # its work after a pose changed the state meanwhile: the map, most of it
                live = state_bytes(vo.map.state(copy=False))
            total, biggest = total + max(0, live - s.snapshot.written_bytes), max(biggest, live)
        return total, biggest

    # -- the stream TTL
    def _sweep_loop(self) -> None:
        every = min(60.0, max(0.5, self.ttl_s / 4))
        while not self._stop.wait(every):
            try:
                self.expire()
            except Exception as exc:  # noqa: BLE001 - the store away: the next pass tries again
                log_event(self.w.log, "stream TTL pass failed", logging.WARNING, error=repr(exc))

    def expire(self, client: str | None = None) -> int:
        """Delete the streams (of `client`, or all) idle past the TTL that this worker may delete; how many went."""
        before = time.time() - self.ttl_s
        return sum(self._delete_idle(stream) for stream in self.w.store.idle_streams(before, client))

    def _delete_idle(self, stream: str) -> bool:
        w = self.w
        if not w.owns(stream):  # another shard's or member's: its worker decides
            return False
        epoch = None
        if w.leases is not None:  # placement members: deleted under the stream's lease, as every write is
            epoch, _ = w.leases.acquire(stream)
            if epoch is None:
                return False

        def delete():
            usage = w.store.stream_usage(stream)
            if usage is None or usage[2] >= time.time() - self.ttl_s:  # written meanwhile
                return None
            poses = w.store.delete_stream(stream, epoch=epoch)
            return usage, poses, self._map_store().delete_stream(stream) if w.store.has_map_tiles() else 0

        deleted = w.forget_idle(stream, delete)  # a live session is never deleted
        if deleted is None:
            return False
        usage, poses, tiles = deleted
        w.stats.inc("streams_expired")
        idle_s = round(time.time() - usage[2])
        log_event(
            w.log, "idle stream deleted (stream_ttl_s)", stream=stream, idle_s=idle_s, poses=poses, map_tiles=tiles
        )
        return True

    def _map_store(self):
        if self._maps is None:
            from occvo_services.store.factory import open_map_store

            self._maps = open_map_store(self.w.config.store_url)
        return self._maps
