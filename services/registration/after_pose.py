"""A frame's work after its pose, in the stream's after-pose thread (loop closure, map update, the second store
write, a relocalised pose, the snapshot schedule), niced below the lanes unless a lane waits for it; its tiles go out
in the stream's map thread."""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import Future

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.registration.kernels import use_threads
from occvo_services.os_tuning import hold_priority, lower_priority, name_os_thread, release_priority
from occvo_services.registration.state import StreamState
from occvo_services.telemetry import log_event


class AfterPose:
    """RegistrationWorker's work after a pose."""

    def _after_pose(self, stream: str, st: StreamState, msg, *rest, head_start: bool = False) -> None:
        """A frame's work after its pose (_after_pose_steps: OccVO.complete and _finish, their second store write, a
        relocalised pose, the map update and the snapshot schedule). A failure is reported as a lane reports one."""
        if head_start:
            st.head_start.wait(self.config.pose_head_start_ms / 1000.0)
        st.tail_tid = threading.get_native_id()
        try:
            self._after_pose_steps(stream, st, msg, *rest)
        except Exception as exc:  # noqa: BLE001 - a worker never dies of one frame
            self.report_error(stream, "internal", f"{type(exc).__name__}: {exc}", seq=msg.seq)
            log_event(self.log, "stage failed", logging.ERROR, stream=stream, error=repr(exc))
        finally:
            with st.tail_lock:
                st.tail_running = False
                if st.tail_boosted:  # niced again for the next frame's work
                    release_priority(st.tail_tid)
                    st.tail_boosted = False

    def _boost_tail(self, st: StreamState) -> None:
        """The lane is about to wait for its stream's work after the last pose: that work now holds up a pose, so it
        runs at the lane's priority until it ends (priority inheritance; without it a niced loop closure waited
        behind every other stream's lane, up to 0.7 s). Raising a thread's priority needs CAP_SYS_NICE or an
        RLIMIT_NICE that allows it (the systemd unit sets LimitNICE); without either the work stays niced."""
        with st.tail_lock:
            if not st.tail_running or st.tail_tid is None or st.tail_boosted:
                return
            if hold_priority(st.tail_tid, os.getpriority(os.PRIO_PROCESS, threading.get_native_id())):
                st.tail_boosted = True
                self.stats.inc("after_pose_boosted")
            elif not self._boost_refused:
                self._boost_refused = True
                log_event(
                    self.log,
                    "cannot raise a waited-for after-pose thread to the lanes' priority (needs "
                    "CAP_SYS_NICE or RLIMIT_NICE, e.g. LimitNICE=+0): it finishes niced",
                    logging.WARNING,
                )

    def _background_thread(self) -> None:
        """Start of a thread doing work off the poses' path: after_pose_nice below the lanes. Its own kernels (tiles
        restored, evicted, snapshot copies) run on one thread; OccVO.complete goes to the worker's kernel team
        (StreamLanes._kernels), the one thread of the process whose kernels run on several."""
        name_os_thread()
        use_threads(1)
        if not lower_priority(self.config.after_pose_nice):
            log_event(
                self.log,
                "cannot lower a background thread's priority here; it runs at the lanes'",
                logging.WARNING,
                thread=threading.current_thread().name,
            )

    def _after_pose_steps(
        self,
        stream: str,
        st: StreamState,
        msg,
        reg,
        frame: OccupancyFrame,
        digest: bytes,
        pose_m: np.ndarray,
        restart: bool,
        t0: float,
        pose_out: Future,
        entered: int,
    ) -> None:
        t_tail = time.perf_counter()
        registered = set(reg.timings_ms)  # complete() adds its stages to the same stopwatch
        publish = True if restart else None  # None: now or with a later frame's (Paging._map_due)
        result, restored, evicted, cut = self._finish(stream, st, reg, frame, msg.seq, publish, entered)
        if not pose_out.result():  # not committed: nothing of it is stored or published (the lane rebuilds the state)
            return
        t_finished = time.perf_counter()
        relocalised = result.loop_correction is not None
        if relocalised:
            self.stats.inc("loop_closures")
            log_event(
                self.log,
                "loop closed",
                stream=stream,
                seq=msg.seq,
                correction_m=round(float(np.linalg.norm(result.pose[:3, 3] - pose_m[:3, 3])), 3),
            )
        if self.store is not None and (relocalised or evicted or st.pending_restored):
            try:
                self.store.finish_frame(
                    stream,
                    msg.seq,
                    np.asarray(result.pose, float) if relocalised else None,
                    evicted=evicted,
                    restored=st.pending_restored,
                )
            except Exception as exc:  # noqa: BLE001 - the journal has the frame: a resume redoes this part
                return self._store_failed(
                    stream, st, msg.seq, exc, "pose stored and published, its map update not stored"
                )
        st.pending_restored = []
        if relocalised:  # supersedes the pose published above
            timings = {"loop_closure": float(result.timings_ms.get("loop_closure", 0.0))}
            self._publish_pose(
                stream, st, msg.seq, msg.stamp, np.asarray(result.pose, float), "relocalised", digest, timings, False
            )
        # the tiles are cut from the copy and sent in the stream's map thread, beside the next frame's registration;
        # one frame's tiles at most wait there (the copy of the last one's is not kept longer). At the lanes' priority:
        # it holds the GIL for most of its work, and a niced holder the cores pass over would stall the lane waiting
        # for the GIL (the after-pose thread's boost covers only the waits for its end)
        t_map = time.perf_counter()
        if cut is not None:
            self._map_done(st)
            st.map_tail = st.map_thread.submit(self._send_tiles, stream, st, msg.seq, restart, cut, evicted, restored)
        else:
            self.stats.inc("map_updates_coalesced")
        t_end = time.perf_counter()
        for k, v in result.timings_ms.items():
            if k not in registered:
                self.stats.observe(f"complete.{k}", float(v))
        self.stats.observe("complete", st.complete_ms)
        self.stats.observe("map_extract", st.extract_ms)
        self.stats.observe("map_wait", (t_end - t_map) * 1000.0)  # the last frame's tiles not sent yet
        self.stats.observe("after_pose_store", (t_map - t_finished) * 1000.0)
        if self.store is not None:
            self.stats.observe("map_restore", st.restore_ms)
            self.stats.observe("map_evict", st.evict_ms)
        self.stats.observe("frame_after_pose", (t_end - t_tail) * 1000.0)
        if t_end - t_tail > self.config.slow_after_pose_s:  # the next frame of the stream waits for this
            log_event(
                self.log,
                "slow work after a pose",
                logging.WARNING,
                stream=stream,
                seq=msg.seq,
                ms=round((t_end - t_tail) * 1000.0),
                timings_ms={k: round(v, 1) for k, v in result.timings_ms.items()},
                finish_ms=round((t_finished - t_tail) * 1000.0),
                extract_ms=round(st.extract_ms, 1),
                restore_ms=round(st.restore_ms, 1),
                evict_ms=round(st.evict_ms, 1),
                store_ms=round((t_map - t_finished) * 1000.0),
                map_wait_ms=round((t_end - t_map) * 1000.0),
                relocalised=relocalised,
            )
        self.stats.observe("stage_total", (time.perf_counter() - t0) * 1000.0)
        if self.store is not None:
            st.since_snapshot += 1
            due = st.snapshot_retry or (
                st.since_snapshot >= self.config.snapshot_every and self._snapshot_affordable(st)
            )
            if due and st.snapshot_idle.is_set():
                self._queue_snapshot(stream, st)

    def _send_tiles(self, stream: str, st: StreamState, seq: int, restart: bool, cut, evicted, restored) -> None:
        """The stream's map thread: one frame's tiles cut and sent (MapPublisher._publish_map), in frame order."""
        try:
            t0 = time.perf_counter()
            sent = self._publish_map(stream, st, seq, restart, cut, evicted, restored)
            self.stats.observe("map_publish", (time.perf_counter() - t0) * 1000.0 - (st.tiling_ms - st.extract_ms))
            self.stats.observe("tiling", st.tiling_ms)
            self.stats.observe("map_update", (time.perf_counter() - t0) * 1000.0 + st.extract_ms)
            if sent[0]:
                self.stats.inc("tiles_sent", sent[0])
        except Exception as exc:  # noqa: BLE001 - a worker never dies of one frame's tiles
            self.report_error(stream, "internal", f"map update of seq {seq}: {type(exc).__name__}: {exc}", seq=seq)
            log_event(self.log, "stage failed", logging.ERROR, stream=stream, error=repr(exc))
