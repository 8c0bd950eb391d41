"""Durability: every pose committed to the store before it is published, snapshots written by one writer thread, and a
stream resumed from its snapshot plus journal; the last snapshots at shutdown."""

from __future__ import annotations

import logging
import time

import numpy as np

from occvo_core.registration.voxel_map import copied
from occvo_schemas import keys
from occvo_services.array_pack import unpack_arrays
from occvo_services.registration.state import StreamState
from occvo_services.telemetry import log_event


class Durability:
    """RegistrationWorker's durable state (services/store.py)."""

    def after_leaving(self) -> None:
        """Off the network (the frames in hand finished): end the streams' after-pose threads, then snapshot every
        stream with unsnapshotted frames."""
        self._team.shutdown(wait=False)  # idle unless a lane's frame did not finish in time
        for stream, st in list(self.states.items()):
            lane = self.lanes.get(stream)
            if st.after_pose is not None and not (lane is not None and lane.thread.is_alive()):
                st.after_pose.shutdown(wait=True)  # drained already: its thread ends now, not at interpreter exit
                if st.map_thread is not None:
                    st.map_thread.shutdown(wait=True)
        if self.store is None:
            return
        t0 = time.perf_counter()
        self._snapshots.put(None)
        self._snapshot_writer.join()
        self._shutdown_step("queued snapshots written", t0)
        for stream, st in list(self.states.items()):
            lane = self.lanes.get(stream)
            if lane is not None and lane.thread.is_alive():
                continue  # its frame in hand did not finish in time: do not touch its OccVO from here
            if st.vo is not None and (st.since_snapshot > 0 or st.snapshot_retry):
                t0 = time.perf_counter()
                # in place: no lane steps it any more
                self._write_snapshot(stream, st, st.seqs[-1], self.store.created(stream), st.vo.state_dict(copy=False))
                self._shutdown_step("snapshot at shutdown", t0, stream=stream, map_voxels=len(st.vo.map))
        t0, sizes = time.perf_counter(), self.store.file_sizes_mb()  # the WAL is checkpointed into the file on close
        self.store.close()
        self._shutdown_step("store closed", t0, **sizes)

    def _shutdown_step(self, step: str, t0: float, **fields) -> None:
        """Log a shutdown step's time; a slow one at WARNING, since a supervisor's stop timeout may cut it short."""
        took = time.perf_counter() - t0
        log_event(self.log, step, logging.WARNING if took > 5.0 else logging.INFO, seconds=round(took, 2), **fields)

    def _store_failed(self, stream: str, st: StreamState, seq: int, exc: Exception, what: str) -> None:
        """A write failed (e.g. disk full): drop the in-memory state; the stream resumes from the store at its next
        frame (replaying the journal redoes what was not stored)."""
        st.vo = None  # the tiles too are started again by the resume
        self.report_error(
            stream,
            "internal",
            f"seq {seq} {what} ({type(exc).__name__}: {exc}); the stream resumes from the store at its next frame",
            keys.occupancy(stream),
            seq,
        )

    def _snapshot_affordable(self, st: StreamState) -> bool:
        """Whether a snapshot now keeps the stream's snapshots within snapshot_max_share of its time: the cost of
        one, from the state's size at this worker's last measured speed, against the time since the stream's last
        snapshot, start or resume (so a short stream is not snapshotted at once: the journal covers it)."""
        share = self.config.snapshot_max_share
        if share is None:
            return True
        size = _nbytes(st.vo.state_dict(copy=False))
        return time.monotonic() - st.snapshot_since >= size * self._snapshot_s_per_byte / share

    def _queue_snapshot(self, stream: str, st: StreamState) -> None:
        """Copy the state for the snapshot writer (a few ms): the lane steps on while the copy is written."""
        t0 = time.perf_counter()
        state = {k: copied(v) for k, v in st.vo.state_dict(copy=False).items()}  # the big ones without the GIL
        st.snapshot_idle.clear()
        st.since_snapshot, st.snapshot_retry = 0, False
        self._snapshots.put((stream, st, st.seqs[-1], self.store.created(stream), state))
        self.stats.observe("snapshot_copy", (time.perf_counter() - t0) * 1000.0)

    def _write_snapshots(self) -> None:
        """The snapshot writer thread: one snapshot at a time, in queue order, until the None of shutdown."""
        self._background_thread()
        while (item := self._snapshots.get()) is not None:
            if callable(item):  # a reset stream's old snapshot to delete, in order with its writes
                try:
                    item()
                except Exception as exc:  # noqa: BLE001 - only space is lost; the writer goes on
                    log_event(self.log, "deleting an old snapshot failed", logging.WARNING, error=repr(exc))
                continue
            self._write_snapshot(*item)
            del item  # the copy goes before the next one is waited for

    def _write_snapshot(self, stream: str, st: StreamState, seq: int, created: float | None, state: dict) -> None:
        t0 = time.perf_counter()
        try:
            if self.store.write_snapshot(stream, seq, state, created):
                self.stats.inc("snapshots")
            took = time.perf_counter() - t0
            st.snapshot_since = time.monotonic()
            self._snapshot_s_per_byte = took / max(1, _nbytes(state))
            self.stats.observe("snapshot", took * 1000.0)
        except Exception as exc:  # noqa: BLE001 - the journal keeps the frames; retried at the stream's next frame
            st.snapshot_retry = True
            self.report_error(
                stream,
                "internal",
                f"snapshot after seq {seq} failed: {type(exc).__name__}: {exc}",
                keys.occupancy(stream),
                seq,
            )
        finally:
            st.snapshot_idle.set()

    def drain(self) -> None:
        """Wait for every stream's work after its last pose (its map update, loop closure, snapshot queueing)."""
        for st in list(self.states.values()):
            st.head_start.set()
            if st.tail is not None:
                st.tail.result()
            self._map_done(st)

    def snapshots_written(self, timeout: float | None = None) -> bool:
        """Wait until no snapshot is queued or being written (tests and benchmarks)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        self.drain()
        for st in list(self.states.values()):
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not st.snapshot_idle.wait(left):
                return False
        return True

    def _resume(self, stream: str, st: StreamState) -> None:
        """Rebuild the stream's OccVO from its snapshot and journal, as it was after the last committed frame."""
        t0 = time.perf_counter()
        self._map_done(st)  # the tiles of the frames before: the resume starts the stream's tiles again
        st.snapshot_idle.wait()  # a snapshot being written would delete journal rows between our two reads
        vo = self._OccVO(self.occvo_config, threads=self.config.kernel_threads)
        snap = self.store.snapshot(stream)
        snap_seq = None
        if snap is not None:
            snap_seq, blob = snap
            vo.load_state_dict(unpack_arrays(blob))
        st.vo = vo
        st.ego_xy = vo.poses[-1][:2, 3].copy() if snap is not None and len(vo.poses) else None
        st.cold = self.store.cold_index(stream, as_of_seq=snap_seq if snap_seq is not None else -1)
        st.cold_digest, st.pending_restored, st.tiles, st.restored_for_next = {}, [], {}, []
        journal = self.store.journal(stream, snap_seq)
        if st.ego_xy is not None:  # a snapshot of a worker that restored the near map at the next frame: do it now
            st.restored_for_next = self._restore(stream, st, self._near(st))
        worst = 0.0
        st.send_all_tiles = True  # the map service may lack the last frames' tiles
        for i, (seq, frame) in enumerate(
            journal
        ):  # the same restores and evictions as the first time, so the same poses
            last = i == len(journal) - 1
            result, restored, evicted, cut = self._advance(stream, st, frame, seq, publish=last)
            if last:  # it may have stopped before its map update was stored or published: do both again
                self._finish_last(stream, st, seq, result, evicted)
                self._publish_map(stream, st, seq, False, cut, evicted, restored)
            st.pending_restored = []
            stored = st.stored(seq)
            diff = float(np.abs(np.asarray(result.pose) - stored.pose).max()) if stored is not None else np.inf
            worst = max(worst, diff)
        now = self.store.cold_index(stream)
        if worst > 0 or now != st.cold:
            self.report_error(
                stream,
                "internal",
                f"resume replayed {len(journal)} journaled frames: max pose difference "
                f"{worst:.3e} m, cold tiles {'equal' if now == st.cold else 'differ'} (expected 0 and equal); "
                "the stored poses stand",
                keys.occupancy(stream),
            )
            st.cold = now
        st.since_snapshot, st.snapshot_since = len(journal), time.monotonic()
        self.stats.inc("resumes")
        log_event(
            self.log,
            "stream resumed",
            stream=stream,
            snapshot_seq=snap_seq,
            journal_frames=len(journal),
            last_seq=st.seqs[-1],
            cold_tiles=len(st.cold),
            ms=round((time.perf_counter() - t0) * 1000.0, 1),
        )

    def _finish_last(self, stream: str, st: StreamState, seq: int, result, evicted: dict) -> None:
        """The journal's last frame may have been stopped between its pose and the rest (its map update, evictions,
        a loop closure's relocalised pose): the replay just redid that part; store what the store lacks of it."""
        stored = st.stored(seq)
        pose = np.asarray(result.pose, float)
        relocalised = (
            result.loop_correction is not None and stored is not None and not np.array_equal(stored.pose, pose)
        )
        if not relocalised and self.store.cold_index(stream) == st.cold:
            return
        self.store.finish_frame(
            stream, seq, pose if relocalised else None, evicted=evicted, restored=st.pending_restored
        )
        log_event(
            self.log,
            "finished the last journaled frame",
            stream=stream,
            seq=seq,
            relocalised=relocalised,
            evicted=len(evicted),
            restored=len(st.pending_restored),
        )
        if relocalised:
            self._publish_pose(stream, st, seq, stored.stamp, pose, "relocalised", stored.digest, {}, False)


def _nbytes(state: dict[str, np.ndarray]) -> int:
    """A state's size: what a snapshot of it writes."""
    return sum(a.nbytes for a in state.values())
