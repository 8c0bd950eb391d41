"""Placement "members": the live registration workers share the streams through the store's leases. A stream stays
with the worker holding its lease while that worker lives; a new stream, or one whose owner is gone, goes to the
live worker with the fewest streams (ties: rendezvous hashing, keys.owner_of), so a worker that joins takes new
streams and one that leaves moves only its own. The lease's fencing epoch makes the owner the stream's only writer:
a worker that was paused or cut off and comes back cannot write over the new owner."""

from __future__ import annotations

import collections
import logging
import threading

import zenoh

from occvo_schemas import keys
from occvo_services.telemetry import log_event

MAX_STREAMS_KNOWN = 4096  # streams whose owner a worker remembers (ids are the clients' to invent)


class Placement:
    """Which live worker owns each stream, as this worker sees it (the lease holder, else the least loaded)."""

    def __init__(self, me: str, store, lease_s: float, log):
        self.me, self.store, self.lease_s, self.log = me, store, lease_s, log
        self.live = {me}
        self._owners: dict[str, str] = {}  # stream -> its owner, while that worker lives
        self._lock = threading.Lock()

    def declare(self, session: zenoh.Session):
        return session.liveliness().declare_subscriber(keys.registration_shard(0, 0, "*"), self._on_token, history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        worker = str(sample.key_expr).rsplit("/", 1)[1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.live.add(worker)
            elif worker != self.me:
                self.live.discard(worker)
                self._owners = {s: w for s, w in self._owners.items() if w != worker}
        log_event(self.log, "registration workers", live=sorted(self.live))

    def members(self) -> int:
        """How many registration workers are live now."""
        with self._lock:
            return len(self.live)

    def is_live(self, worker: str | None) -> bool:
        with self._lock:
            return worker in self.live

    def owner(self, stream: str) -> str:
        """The stream's owner: its lease holder while that worker lives, else the least-loaded live worker, which the
        first worker to decide records as the lease's owner (every other then reads that decision: no two workers
        can each leave the stream to the other)."""
        with self._lock:
            owner = self._owners.get(stream)
        if owner is not None:
            return owner
        for _ in range(3):  # another worker's decision may land between a read and a write: read it then
            holder = self.store.owner_of(stream)
            if holder is not None and self.is_live(holder):
                owner = holder
                break
            chosen = self._least_loaded(stream)
            # a holder that is not live is gone: its lease is taken (a free or expired one reads as no holder)
            if self.store.acquire(stream, chosen, self.lease_s, take_from=holder) is not None:
                owner = chosen
                break
        else:
            owner = self.store.owner_of(stream) or self.me
        with self._lock:
            self._owners[stream] = owner
            if len(self._owners) > MAX_STREAMS_KNOWN:  # the oldest looked-up stream is looked up again if it comes
                del self._owners[next(iter(self._owners))]
        return owner

    def _least_loaded(self, stream: str) -> str:
        with self._lock:
            live = set(self.live)
        held = collections.Counter(lease.owner for lease in self.store.leases() if lease.remaining_s > 0)
        fewest = min(held[w] for w in live)
        return keys.owner_of(stream, [w for w in live if held[w] == fewest])

    def forget(self, stream: str) -> None:
        """The stream's owner is looked up again at its next frame (this worker lost its lease)."""
        with self._lock:
            self._owners.pop(stream, None)


class Leases:
    """This worker's stream leases: taken before its first write of a stream (at once from an owner that is gone),
    renewed while the worker lives, given back when it stops."""

    def __init__(self, store, me: str, lease_s: float, placement: Placement, log, serving=frozenset):
        self.store, self.me, self.lease_s, self.placement, self.log = store, me, lease_s, placement, log
        self.serving = serving  # () -> the streams this worker serves now: their lease rows stay
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._renew, name="lease-renewal", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def acquire(self, stream: str) -> tuple[int | None, str | None]:
        """(epoch, None) once this worker holds the stream's lease; (None, owner) while a live worker holds it."""
        holder = self.store.owner_of(stream)
        lost = holder if holder not in (None, self.me) and not self.placement.is_live(holder) else None
        epoch = self.store.acquire(stream, self.me, self.lease_s, take_from=lost)
        return (epoch, None) if epoch is not None else (None, self.store.owner_of(stream))

    def release(self, stream: str) -> None:
        try:
            self.store.release(stream, self.me)
        except Exception as exc:  # noqa: BLE001 - it expires then; the next owner waits at most lease_s
            log_event(self.log, "releasing a lease failed", logging.WARNING, stream=stream, error=repr(exc))

    def _renew(self) -> None:
        while not self._stop.wait(self.lease_s / 3):
            try:
                self.store.renew(self.me, self.lease_s)
                # placed, then refused (admission, memory) or never valid: a row a stream that stored nothing leaves
                dropped = self.store.drop_unused_leases(self.me, sorted(self.serving()))
                if dropped:
                    log_event(self.log, "leases of streams that stored nothing deleted", leases=dropped)
            except Exception as exc:  # noqa: BLE001 - the store is away: commits fail and say so; retried
                log_event(self.log, "renewing leases failed", logging.WARNING, error=repr(exc))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
