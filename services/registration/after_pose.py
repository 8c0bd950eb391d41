"""The work after a pose, a session's second part (AfterPose): it owns the stream's OccVO, its paging, its map output
and its snapshot schedule. Each frame the pose path registered comes as a RegisteredFrame and runs here, in the
session's after-pose strand: complete (loop closure, the voxel pfilter's map update, paging), store what that changed,
a relocalised pose, the map update, the snapshot schedule. It stores and publishes nothing unless the pose went out
(frame.pose_out). A reopen rebuilds the OccVO here (resume.py replays the journal through complete)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.registration.map_output import MapOutput
from occvo_services.registration.paging import Pager
from occvo_services.registration.resume import load_snapshot, resume
from occvo_services.registration.snapshots import SnapshotSchedule
from occvo_services.store.errors import StoreUnavailable
from occvo_services.telemetry import log_event

if TYPE_CHECKING:
    from occvo_services.registration.frame_job import RegisteredFrame, SessionContext
    from occvo_services.registration.scheduling import StreamThreads
    from occvo_services.store.records import StoredPose


class PoseSide(Protocol):
    """What the work after a pose asks of its session's pose path (pose_path.PosePath)."""

    may_write: bool

    def publish_pose(self, seq, stamp, pose_m, status, digest, timings, restart, covariance=None) -> None: ...
    def stored(self, seq: int) -> StoredPose | None: ...
    def last_seq(self) -> int | None: ...
    def frames_waiting(self, entered: int) -> bool: ...
    def fence(self) -> dict: ...
    def store_failed(self, seq: int, exc: Exception, what: str) -> None: ...


class Completed(NamedTuple):
    """What complete() hands on: OccVO.complete's result, tiles restored, blocks evicted, the map's cut (None: its
    change waits for a later frame's) and the ms of its steps (complete, restore, evict)."""

    result: object
    restored: list
    evicted: dict
    cut: tuple | None
    ms: dict


class AfterPose:
    """A stream's OccVO and what follows a pose on it; nothing outside writes these fields."""

    def __init__(self, stream: str, ctx: SessionContext, threads: StreamThreads, pose: PoseSide):
        self.stream, self.ctx, self.threads, self.pose = stream, ctx, threads, pose
        c = ctx.config
        self.vo = None  # None until this process registered or resumed the stream
        self.pager = Pager(stream, ctx.store, ctx.stats, c.working_radius_m, c.tile_m)
        self.map = MapOutput(stream, c, ctx.stats, ctx.log, ctx.put, ctx.report_error)
        self.snapshot = SnapshotSchedule()

    # -- a registered frame ------------------------------------------------------------------------------------------
    def run(self, frame: RegisteredFrame) -> None:
        """The phases after a pose; a failure is reported as a lane reports one (a worker never dies of one frame)."""
        try:
            self._steps(frame)
        except StoreUnavailable as exc:  # e.g. cold tiles not read back: the state is rebuilt from the store
            self.pose.store_failed(frame.msg.seq, exc, "registered, its work after the pose not done")
        except Exception as exc:  # noqa: BLE001
            self.ctx.report_error(self.stream, "internal", f"{type(exc).__name__}: {exc}", seq=frame.msg.seq)
            log_event(self.ctx.log, "stage failed", logging.ERROR, stream=self.stream, error=repr(exc))

    def _steps(self, f: RegisteredFrame) -> None:
        t_tail = time.perf_counter()
        seq = f.msg.seq
        publish = True if f.restart else None  # None: now or with a later frame's (MapOutput.due)
        done = self.complete(f.reg, f.frame, seq, publish, f.entered)
        result, restored, evicted, cut = done[:4]
        if not f.pose_out.result():  # not committed: nothing of it is stored or published (the lane rebuilds it)
            return
        t_finished = time.perf_counter()
        relocalised = result.loop_correction is not None
        if relocalised:
            self.ctx.stats.inc("loop_closures")
            moved = float(np.linalg.norm(result.pose[:3, 3] - f.pose_m[:3, 3]))
            log_event(self.ctx.log, "loop closed", stream=self.stream, seq=seq, correction_m=round(moved, 3))
        if not self._store(seq, np.asarray(result.pose, float) if relocalised else None, evicted):
            return
        if relocalised:  # supersedes the pose published before
            timings = {"loop_closure": float(result.timings_ms.get("loop_closure", 0.0))}
            pose_m = np.asarray(result.pose, float)
            self.pose.publish_pose(seq, f.msg.stamp, pose_m, "relocalised", f.digest, timings, False)
        # the tiles are cut and sent in the stream's map thread, beside the next frame's registration, at the lanes'
        # priority: it holds the GIL for most of its work, and a niced holder would stall the lane waiting for the GIL
        t_map = time.perf_counter()
        if cut is not None:
            self.threads.submit_map(self.map.send, seq, f.restart, cut, evicted, restored)
        else:
            self.ctx.stats.inc("map_updates_coalesced")
        self._observe(f, done, (t_tail, t_finished, t_map, time.perf_counter()), relocalised)
        self._schedule_snapshot()

    def complete(self, reg, frame: OccupancyFrame, seq: int, publish: bool | None, entered: int = 0) -> Completed:
        """After the pose: loop closure and map update (OccVO.complete), keep every tile wholly resident or wholly
        cold, evict far map, and bring back the cold map near the new pose, which the next frame registers against.
        publish None: when MapOutput.due or tiles come back or leave now; else the change waits for a later frame's
        cut. A resume's replay of the journal goes the same way, so it reproduces the poses."""
        vo, pager = self.vo, self.pager
        t_complete = time.perf_counter()
        result, _ = self.ctx.scheduler.kernels(vo, vo.complete, reg)  # the next frame's registration waits for it
        pose = np.asarray(result.pose, float)
        t0 = time.perf_counter()
        restored = list(pager.restored_for_next)
        if pager.cold:  # a frame that reached into an evicted tile: bring the rest back, so the tile stays whole
            restored += pager.restore(vo, pager.reached(frame, pose))
        t_map = time.perf_counter()
        if publish is None:
            publish = bool(restored) or self.map.due(self.pose.frames_waiting(entered)) or pager.evicts(vo, pose)
        cut = self.map.cut(vo) if publish else self.map.hold()  # only the part changed since the last cut again
        t_evict = time.perf_counter()
        evicted = pager.evict_far(vo, seq, pose)
        evict_ms = (time.perf_counter() - t_evict) * 1000.0
        pager.moved_to(pose)
        t_near = time.perf_counter()
        pager.restore_near(vo)  # published with the next frame's tiles (they are cut then); committed with this frame
        restore_ms = (t_map - t0 + time.perf_counter() - t_near) * 1000.0
        ms = {"complete": (t0 - t_complete) * 1000.0, "restore": restore_ms, "evict": evict_ms}
        return Completed(result, restored, evicted, cut, ms)

    def _store(self, seq: int, relocalised_pose, evicted: dict) -> bool:
        """The frame's second write: a relocalised pose, tiles evicted and restored. False if it failed."""
        store, pager = self.ctx.store, self.pager
        if store is not None and (relocalised_pose is not None or evicted or pager.pending_restored):
            try:
                restored = pager.pending_restored
                fence = self.pose.fence()
                store.finish_frame(self.stream, seq, relocalised_pose, evicted=evicted, restored=restored, **fence)
            except Exception as exc:  # noqa: BLE001 - the journal has the frame: a resume redoes this part
                self.pose.store_failed(seq, exc, "pose stored and published, its map update not stored")
                return False
        pager.restores_stored()
        return True

    def _observe(self, f: RegisteredFrame, done: Completed, marks: tuple, relocalised: bool) -> None:
        """The after-pose stages in the worker's stats; a slow one logged (the stream's next frame waits for it)."""
        t_tail, t_finished, t_map, t_end = marks
        result, ms = done.result, done.ms
        stats, config = self.ctx.stats, self.ctx.config
        for k, v in result.timings_ms.items():
            if k not in f.reg_timings:
                stats.observe(f"complete.{k}", float(v))
        stats.observe("complete", ms["complete"])
        stats.observe("map_extract", self.map.extract_ms)
        stats.observe("map_wait", (t_end - t_map) * 1000.0)  # the last frame's tiles not sent yet
        stats.observe("after_pose_store", (t_map - t_finished) * 1000.0)
        if self.ctx.store is not None:
            stats.observe("map_restore", ms["restore"])
            stats.observe("map_evict", ms["evict"])
        stats.observe("frame_after_pose", (t_end - t_tail) * 1000.0)
        if t_end - t_tail > config.slow_after_pose_s:
            log_event(
                self.ctx.log,
                "slow work after a pose",
                logging.WARNING,
                stream=self.stream,
                seq=f.msg.seq,
                ms=round((t_end - t_tail) * 1000.0),
                timings_ms={k: round(v, 1) for k, v in result.timings_ms.items()},
                finish_ms=round((t_finished - t_tail) * 1000.0),
                extract_ms=round(self.map.extract_ms, 1),
                restore_ms=round(ms["restore"], 1),
                evict_ms=round(ms["evict"], 1),
                store_ms=round((t_map - t_finished) * 1000.0),
                map_wait_ms=round((t_end - t_map) * 1000.0),
                relocalised=relocalised,
            )
        stats.observe("stage_total", (time.perf_counter() - f.t_valid) * 1000.0)

    def _schedule_snapshot(self) -> None:
        """With a store: a snapshot once snapshot_every frames were committed since the last and its cost is within
        snapshot_max_share of the stream's time (or the last one failed)."""
        if self.ctx.store is None or not self.pose.may_write:
            return
        sched, config = self.snapshot, self.ctx.config
        sched.committed()
        due = sched.retry or (
            sched.since >= config.snapshot_every
            and self.ctx.snapshots.affordable(sched, self.vo.state_dict(copy=False), config.snapshot_max_share)
        )
        if due and sched.idle.is_set():
            self.ctx.snapshots.queue(self.stream, sched, self.pose.last_seq(), self.vo, self.pose.fence())

    # -- the OccVO's life ----------------------------------------------------------------------------------------------
    def restart(self) -> None:
        """Seq 0 (or a stream's first frame): the OccVO reset, paging and tiles started again."""
        self.threads.wait_map()
        self.vo = self.vo or self.ctx.occvo(self.ctx.occvo_config, threads=self.ctx.config.kernel_threads)
        self.vo.reset()
        self.pager.reset()
        self.map.reset()
        self.snapshot.restart()

    def reopen(self) -> None:
        """Rebuild the OccVO from the stream's snapshot and journal, as it was after the last committed frame."""
        self.ctx.catch_up.begin(self.stream)
        t0 = time.perf_counter()
        self.threads.wait_map()  # the tiles of the frames before: the resume starts the stream's tiles again
        self.snapshot.idle.wait()  # a snapshot being written would delete journal rows between our two reads
        self.vo, snap_seq = load_snapshot(self.ctx, self.stream)
        resume(self, snap_seq, t0)

    def share_cores(self, threads: int) -> None:
        """The kernel threads the OccVO's next frame may use (Scheduler.fair_threads)."""
        self.vo.threads = threads

    def drop(self) -> None:
        """A write or read failed: the OccVO goes; the stream resumes from the store at its next frame."""
        self.vo = None

    def flush_map(self) -> None:
        """The tiles held back for a frame that did not come (refused, or none followed)."""
        last = self.pose.last_seq()
        if self.map.pending and self.vo is not None and last is not None and self.threads.map is not None:
            cut = self.map.cut(self.vo)
            self.threads.submit_map(self.map.send, last, False, cut, {}, [])

    def close(self) -> None:
        """An idle stream (its threads ended): with a store its OccVO is snapshotted and dropped (the next frame
        reopens it from the store), without one it stays in memory (it is the only copy)."""
        if self.ctx.store is None or self.vo is None:
            return
        self.snapshot.idle.wait()
        self.save()
        self.vo = None  # heap trimmed by the worker
        self.pager.reset()
        self.map.reset()

    def save(self) -> int | None:
        """A snapshot of the state in place, in the calling thread, if it has frames no snapshot has and this worker
        may write the stream; the map's voxels written, else None."""
        vo = self.vo  # an idle session retiring meanwhile drops its OccVO (after its own snapshot)
        if vo is None or not self.snapshot.unsaved or not self.pose.may_write:
            return None
        self.ctx.snapshots.write_now(self.stream, self.snapshot, self.pose.last_seq(), vo, self.pose.fence())
        return len(vo.map)
