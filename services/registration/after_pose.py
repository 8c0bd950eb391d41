"""A frame's work after its pose, in its session's after-pose thread: complete (loop closure, the voxel pfilter's map
update, paging), store what that changed, a relocalised pose, the map update, the snapshot schedule. It stores and
publishes nothing unless the pose went out (job.pose_out)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.store.errors import StoreUnavailable
from occvo_services.telemetry import log_event

if TYPE_CHECKING:
    from occvo_services.registration.frame_job import FrameJob
    from occvo_services.registration.session import StreamSession


def after_pose(s: StreamSession, job: FrameJob) -> None:
    """The phases after a pose; a failure is reported as a lane reports one (a worker never dies of one frame)."""
    try:
        _after_pose_steps(s, job)
    except StoreUnavailable as exc:  # e.g. cold tiles not read back: the state is rebuilt from the store
        s.store_failed(job.msg.seq, exc, "registered, its work after the pose not done")
    except Exception as exc:  # noqa: BLE001
        s.ctx.report_error(s.stream, "internal", f"{type(exc).__name__}: {exc}", seq=job.msg.seq)
        log_event(s.ctx.log, "stage failed", logging.ERROR, stream=s.stream, error=repr(exc))


def _after_pose_steps(s: StreamSession, job: FrameJob) -> None:
    t_tail = time.perf_counter()
    seq = job.msg.seq
    publish = True if job.restart else None  # None: now or with a later frame's (MapOutput.due)
    done = complete(s, job.reg, job.frame, seq, publish, job.entered)
    result, restored, evicted, cut = done[:4]
    if not job.pose_out.result():  # not committed: nothing of it is stored or published (the lane rebuilds the state)
        return
    t_finished = time.perf_counter()
    relocalised = result.loop_correction is not None
    if relocalised:
        s.ctx.stats.inc("loop_closures")
        moved = float(np.linalg.norm(result.pose[:3, 3] - job.pose_m[:3, 3]))
        log_event(s.ctx.log, "loop closed", stream=s.stream, seq=seq, correction_m=round(moved, 3))
    if not _store_after_pose(s, seq, np.asarray(result.pose, float) if relocalised else None, evicted):
        return
    if relocalised:  # supersedes the pose published before
        timings = {"loop_closure": float(result.timings_ms.get("loop_closure", 0.0))}
        s.publish_pose(seq, job.msg.stamp, np.asarray(result.pose, float), "relocalised", job.digest, timings, False)
    # the tiles are cut and sent in the stream's map thread, beside the next frame's registration, at the lanes'
    # priority: it holds the GIL for most of its work, and a niced holder would stall the lane waiting for the GIL
    t_map = time.perf_counter()
    if cut is not None:
        s.threads.submit_map(s.map.send, seq, job.restart, cut, evicted, restored)
    else:
        s.ctx.stats.inc("map_updates_coalesced")
    _observe(s, job, done, (t_tail, t_finished, t_map, time.perf_counter()), relocalised)
    _schedule_snapshot(s)


class Completed(NamedTuple):
    """What complete() hands on: OccVO.complete's result, tiles restored, blocks evicted, the map's cut (None: its
    change waits for a later frame's) and the ms of its steps (complete, restore, evict)."""

    result: object
    restored: list
    evicted: dict
    cut: tuple | None
    ms: dict


def complete(s: StreamSession, reg, frame: OccupancyFrame, seq: int, publish: bool | None, entered: int = 0):
    """After the pose: loop closure and map update (OccVO.complete), keep every tile wholly resident or wholly
    cold, evict far map, and bring back the cold map near the new pose, which the next frame registers against.
    publish None: when MapOutput.due or tiles come back or leave now; else the change waits for a later frame's cut.
    A resume's replay of the journal goes the same way, so it reproduces the poses."""
    vo, pager = s.vo, s.pager
    t_complete = time.perf_counter()
    result, _ = s.ctx.scheduler.kernels(vo, vo.complete, reg)  # the next frame's registration waits for it
    pose = np.asarray(result.pose, float)
    t0 = time.perf_counter()
    restored = list(pager.restored_for_next)
    if pager.cold:  # a frame that reached into an evicted tile: bring the rest back, so the tile stays whole
        restored += pager.restore(vo, pager.reached(frame, pose))
    t_map = time.perf_counter()
    if publish is None:
        publish = bool(restored) or s.map.due(s.frames_waiting(entered)) or pager.evicts(vo, pose)
    cut = s.map.cut(vo) if publish else s.map.hold()  # only the part changed since the last cut is cut again
    t_evict = time.perf_counter()
    evicted = pager.evict_far(vo, seq, pose)
    evict_ms = (time.perf_counter() - t_evict) * 1000.0
    pager.ego_xy = pose[:2, 3].copy()
    t_near = time.perf_counter()
    # published with the next frame's tiles (they are cut then); committed with this frame
    pager.restored_for_next = pager.restore(vo, pager.near())
    restore_ms = (t_map - t0 + time.perf_counter() - t_near) * 1000.0
    ms = {"complete": (t0 - t_complete) * 1000.0, "restore": restore_ms, "evict": evict_ms}
    return Completed(result, restored, evicted, cut, ms)


def _store_after_pose(s: StreamSession, seq: int, relocalised_pose, evicted: dict) -> bool:
    """The frame's second write: a relocalised pose, tiles evicted and restored. False if it failed."""
    store, pager = s.ctx.store, s.pager
    if store is not None and (relocalised_pose is not None or evicted or pager.pending_restored):
        try:
            restored = pager.pending_restored
            store.finish_frame(s.stream, seq, relocalised_pose, evicted=evicted, restored=restored, **s.fence())
        except Exception as exc:  # noqa: BLE001 - the journal has the frame: a resume redoes this part
            s.store_failed(seq, exc, "pose stored and published, its map update not stored")
            return False
    pager.pending_restored = []
    return True


def _observe(s: StreamSession, job: FrameJob, done: Completed, marks: tuple, relocalised: bool) -> None:
    """The after-pose stages in the worker's stats; a slow one logged (the stream's next frame waits for it)."""
    t_tail, t_finished, t_map, t_end = marks
    result, ms = done.result, done.ms
    stats, config = s.ctx.stats, s.ctx.config
    for k, v in result.timings_ms.items():
        if k not in job.reg_timings:
            stats.observe(f"complete.{k}", float(v))
    stats.observe("complete", ms["complete"])
    stats.observe("map_extract", s.map.extract_ms)
    stats.observe("map_wait", (t_end - t_map) * 1000.0)  # the last frame's tiles not sent yet
    stats.observe("after_pose_store", (t_map - t_finished) * 1000.0)
    if s.ctx.store is not None:
        stats.observe("map_restore", ms["restore"])
        stats.observe("map_evict", ms["evict"])
    stats.observe("frame_after_pose", (t_end - t_tail) * 1000.0)
    if t_end - t_tail > config.slow_after_pose_s:
        log_event(
            s.ctx.log,
            "slow work after a pose",
            logging.WARNING,
            stream=s.stream,
            seq=job.msg.seq,
            ms=round((t_end - t_tail) * 1000.0),
            timings_ms={k: round(v, 1) for k, v in result.timings_ms.items()},
            finish_ms=round((t_finished - t_tail) * 1000.0),
            extract_ms=round(s.map.extract_ms, 1),
            restore_ms=round(ms["restore"], 1),
            evict_ms=round(ms["evict"], 1),
            store_ms=round((t_map - t_finished) * 1000.0),
            map_wait_ms=round((t_end - t_map) * 1000.0),
            relocalised=relocalised,
        )
    stats.observe("stage_total", (time.perf_counter() - job.t_valid) * 1000.0)


def _schedule_snapshot(s: StreamSession) -> None:
    """With a store: a snapshot once snapshot_every frames were committed since the last and its cost is within
    snapshot_max_share of the stream's time (or the last one failed)."""
    if s.ctx.store is None or not s.may_write:
        return
    sched, config = s.snapshot, s.ctx.config
    sched.since += 1
    due = sched.retry or (
        sched.since >= config.snapshot_every
        and s.ctx.snapshots.affordable(sched, s.vo.state_dict(copy=False), config.snapshot_max_share)
    )
    if due and sched.idle.is_set():
        s.ctx.snapshots.queue(s.stream, sched, s.trajectory.last_seq, s.vo, s.fence())
