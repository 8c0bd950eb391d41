"""Placement "members": the live registration workers share the streams by rendezvous hashing over their liveliness
tokens (keys.owner_of), so a worker that comes or goes moves only the streams it takes or had. The store's lease
with its fencing epoch makes each stream's owner its only writer: a worker that was paused or cut off and comes back
cannot write over the new owner."""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from occvo_schemas import keys
from occvo_services.telemetry import log_event


class Members:
    """The live registration workers, this one included, as their tokens come and go."""

    def __init__(self, me: str, on_change):
        self.me, self.on_change = me, on_change
        self.live = {me}
        self._lock = threading.Lock()

    def declare(self, session: zenoh.Session):
        return session.liveliness().declare_subscriber(keys.registration_shard(0, 0, "*"), self._on_token, history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        worker = str(sample.key_expr).rsplit("/", 1)[1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                changed = worker not in self.live
                self.live.add(worker)
            else:
                changed = worker != self.me and worker in self.live
                self.live.discard(worker)
        if changed:
            self.on_change()

    def owner(self, stream: str) -> str:
        with self._lock:
            return keys.owner_of(stream, self.live)

    def is_live(self, worker: str) -> bool:
        with self._lock:
            return worker in self.live


class Leases:
    """This worker's stream leases in the store: taken before its first write of a stream (from a lost owner at
    once), renewed while the worker lives, given back when a stream moves on."""

    def __init__(self, store, me: str, lease_s: float, members: Members, log):
        self.store, self.me, self.lease_s, self.members, self.log = store, me, lease_s, members, log
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._renew, name="lease-renewal", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def acquire(self, stream: str) -> tuple[int | None, str | None]:
        """(epoch, None) once this worker holds the stream's lease; (None, owner) if a live owner still held it after
        lease_s (it hands the stream over as soon as its queued frames are done)."""
        deadline = time.monotonic() + self.lease_s
        while True:
            owner = self.store.owner_of(stream)
            lost = owner if owner is not None and owner != self.me and not self.members.is_live(owner) else None
            epoch = self.store.acquire(stream, self.me, self.lease_s, take_from=lost)
            if epoch is not None:
                return epoch, None
            if time.monotonic() > deadline or self._stop.is_set():
                return None, owner
            time.sleep(0.05)

    def release(self, stream: str) -> None:
        try:
            self.store.release(stream, self.me)
        except Exception as exc:  # noqa: BLE001 - it expires then; the next owner waits at most lease_s
            log_event(self.log, "releasing a lease failed", logging.WARNING, stream=stream, error=repr(exc))

    def _renew(self) -> None:
        while not self._stop.wait(self.lease_s / 3):
            try:
                self.store.renew(self.me, self.lease_s)
            except Exception as exc:  # noqa: BLE001 - the store is away: commits fail and say so; retried
                log_event(self.log, "renewing leases failed", logging.WARNING, error=repr(exc))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
