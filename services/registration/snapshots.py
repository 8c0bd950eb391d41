"""Snapshots of a session's OccVO: when one is due (SnapshotSchedule, one a session) and the worker's one writer
thread (SnapshotWriter), so a lane steps on while a copy of its state is written."""

from __future__ import annotations

import logging
import queue
import threading
import time

from occvo_core.registration.voxel_map import copied
from occvo_core.state import stored
from occvo_schemas import keys
from occvo_services.telemetry import log_event

SNAPSHOT_BYTES_PER_S = 200e6  # a snapshot's writing speed until this worker has measured one (an SSD's order)


def state_bytes(state: dict) -> int:
    """A state's size: what a snapshot of it writes."""
    return sum(a.nbytes for a in state.values())


class SnapshotSchedule:
    """A session's snapshot bookkeeping."""

    def __init__(self):
        self.since = 0  # frames committed since the last snapshot (the journal holds them)
        self.since_t = time.monotonic()  # the stream's start, resume or last snapshot: what its share is of
        self.idle = threading.Event()  # no snapshot of this stream queued or being written
        self.idle.set()
        self.retry = False  # the last snapshot failed: take one at the next frame
        self.written_bytes = 0  # the state the last snapshot wrote (services/registration/retention.py)

    def restart(self, frames: int = 0) -> None:
        self.since, self.since_t = frames, time.monotonic()

    @property
    def unsaved(self) -> bool:
        return self.since > 0 or self.retry

    def committed(self) -> None:
        """A frame committed since the last snapshot."""
        self.since += 1

    def writing(self) -> None:
        """A snapshot of the stream queued or being written (idle is set again once it is written or failed)."""
        self.idle.clear()

    def taken(self) -> None:
        """A copy of the state taken for the writer: the next snapshot counts from here."""
        self.writing()
        self.since, self.retry = 0, False

    def written(self, state_size: int) -> None:
        self.written_bytes = state_size

    def clock_restarted(self) -> None:
        """A snapshot's write ended: the stream's share of time is counted from now."""
        self.since_t = time.monotonic()

    def failed(self) -> None:
        self.retry = True  # the journal keeps the frames: retried at the stream's next frame


class SnapshotWriter:
    """One thread writing snapshots in queue order (SQLite has one writer a file: a big snapshot must not hold every
    stream's frame commits); its measured speed decides when the next ones are affordable."""

    def __init__(self, store, stats, log, report_error, thread_start):
        self.store, self.stats, self.log, self.report_error = store, stats, log, report_error
        self._queue: queue.Queue = queue.Queue()
        self._s_per_byte = 1 / SNAPSHOT_BYTES_PER_S  # measured by each snapshot written
        self._thread = threading.Thread(target=self._run, args=(thread_start,), name="snapshot-writer", daemon=True)
        self._thread.start()

    def affordable(self, schedule: SnapshotSchedule, state: dict, share: float | None) -> bool:
        """Whether a snapshot now keeps the stream's snapshots within `share` of its time: the cost of one, from the
        state's size at the last measured speed, against the time since the stream's last snapshot, start or resume
        (so a short stream is not snapshotted at once: the journal covers it)."""
        if share is None:
            return True
        return time.monotonic() - schedule.since_t >= state_bytes(state) * self._s_per_byte / share

    def queue(self, stream: str, schedule: SnapshotSchedule, seq: int, vo, fence: dict) -> None:
        """Copy the state for the writer (a few ms): the lane steps on while the copy is written."""
        t0 = time.perf_counter()
        state = {k: copied(v) for k, v in vo.state_dict(copy=False).items()}  # the big ones without the GIL
        schedule.taken()
        self._queue.put((stream, schedule, seq, self.store.created(stream), state, fence))
        self.stats.observe("snapshot_copy", (time.perf_counter() - t0) * 1000.0)

    def forget_old(self, stream: str) -> None:
        """A reset stream's old snapshot deleted, in order with the writes queued before."""
        self._queue.put(lambda: self.store.drop_old_snapshots(stream))

    def write_now(self, stream: str, schedule: SnapshotSchedule, seq: int, vo, fence: dict) -> None:
        """A snapshot of the state in place, in the calling thread (nothing steps this OccVO any more)."""
        schedule.idle.wait()
        schedule.writing()
        self.write(stream, schedule, seq, self.store.created(stream), vo.state_dict(copy=False), fence)

    def write(self, stream: str, schedule: SnapshotSchedule, seq: int, created, state: dict, fence: dict) -> None:
        """The state in its stored form (occvo_core.state.stored: a third smaller). fence: the lease epoch the write
        carries (placement "members"), else nothing."""
        t0 = time.perf_counter()
        try:
            if self.store.write_snapshot(stream, seq, stored(state), created, **fence):
                self.stats.inc("snapshots")
                schedule.written(state_bytes(state))
                self.store.measure(stream)  # its stored bytes, the journal covered gone (a client's store quota)
            took = time.perf_counter() - t0
            schedule.clock_restarted()
            self._s_per_byte = took / max(1, state_bytes(state))
            self.stats.observe("snapshot", took * 1000.0)
        except Exception as exc:  # noqa: BLE001 - the journal keeps the frames; retried at the stream's next frame
            schedule.failed()
            message = f"snapshot after seq {seq} failed: {type(exc).__name__}: {exc}"
            self.report_error(stream, "internal", message, keys.occupancy(stream), seq)
        finally:
            schedule.idle.set()

    def _run(self, thread_start) -> None:
        thread_start()
        while (item := self._queue.get()) is not None:
            if callable(item):
                try:
                    item()
                except Exception as exc:  # noqa: BLE001 - only space is lost; the writer goes on
                    log_event(self.log, "deleting an old snapshot failed", logging.WARNING, error=repr(exc))
                continue
            self.write(*item)
            del item  # the copy goes before the next one is waited for

    def close(self) -> None:
        """Every queued snapshot written, then the thread ends."""
        self._queue.put(None)
        self._thread.join()
