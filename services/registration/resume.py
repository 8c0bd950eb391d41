"""A session reopened from the store: its OccVO rebuilt from the last snapshot plus the journal of the frames
committed after it, with the same restores and evictions as the first time, so the same poses. The after-pose part
(AfterPose.reopen) calls these; they change its state only through its methods and its pager's and map's."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from occvo_schemas import keys
from occvo_services.array_pack import unpack_arrays
from occvo_services.telemetry import log_event

if TYPE_CHECKING:
    from occvo_services.registration.after_pose import AfterPose
    from occvo_services.registration.frame_job import SessionContext


def load_snapshot(ctx: SessionContext, stream: str) -> tuple:
    """(OccVO, seq) of the stream's last snapshot (a new OccVO and None without one); the session adopts the OccVO,
    then resume() brings it to the stream's last committed frame."""
    vo = ctx.occvo(ctx.occvo_config, threads=ctx.config.kernel_threads)
    snap = ctx.store.snapshot(stream)
    if snap is None:
        return vo, None
    vo.load_state_dict(unpack_arrays(snap[1]))
    return vo, snap[0]


def resume(s: AfterPose, snap_seq: int | None, t0: float) -> None:
    """The session's OccVO (load_snapshot's) as it was after the stream's last committed frame: the journal after
    the snapshot replayed. t0: when the resume began."""
    store, stream, vo = s.ctx.store, s.stream, s.vo
    ego_xy = vo.poses[-1][:2, 3].copy() if snap_seq is not None and len(vo.poses) else None
    s.pager.reset(store.cold_index(stream, as_of_seq=snap_seq if snap_seq is not None else -1), ego_xy)
    s.map.reset(send_all=True)  # the map service may lack the last frames' tiles
    journal = store.journal(stream, snap_seq)
    if ego_xy is not None:  # a snapshot of a worker that restored the near map at the next frame: do it now
        s.pager.restore_near(vo)
    worst = _replay(s, journal)
    now = store.cold_index(stream)
    if worst > 0 or now != s.pager.cold:
        s.ctx.report_error(
            stream,
            "internal",
            f"resume replayed {len(journal)} journaled frames: max pose difference {worst:.3e} m, cold tiles "
            f"{'equal' if now == s.pager.cold else 'differ'} (expected 0 and equal); the stored poses stand",
            keys.occupancy(stream),
        )
        s.pager.adopt_cold(now)
    s.snapshot.restart(len(journal))
    s.ctx.stats.inc("resumes")
    log_event(
        s.ctx.log,
        "stream resumed",
        stream=stream,
        snapshot_seq=snap_seq,
        journal_frames=len(journal),
        last_seq=s.pose.last_seq(),
        cold_tiles=len(s.pager.cold),
        ms=round((time.perf_counter() - t0) * 1000.0, 1),
    )


def _replay(s: AfterPose, journal: list) -> float:
    """The journal's frames registered again; returns the largest difference from their stored poses."""
    worst = 0.0
    for i, (seq, frame) in enumerate(journal):
        last = i == len(journal) - 1
        result, restored, evicted, cut, _ = s.complete(s.vo.register(frame), frame, seq, publish=last)
        if last:  # it may have stopped before its map update was stored or published: do both again
            _finish_last(s, seq, result, evicted)
            s.map.publish(seq, False, cut, evicted, restored)
        s.pager.restores_stored()
        stored = s.pose.stored(seq)
        diff = float(np.abs(np.asarray(result.pose) - stored.pose).max()) if stored is not None else np.inf
        worst = max(worst, diff)
    return worst


def _finish_last(s: AfterPose, seq: int, result, evicted: dict) -> None:
    """The journal's last frame may have been stopped between its pose and the rest (its map update, evictions, a
    loop closure's relocalised pose): the replay just redid that part; store what the store lacks of it."""
    store, pager = s.ctx.store, s.pager
    stored = s.pose.stored(seq)
    pose = np.asarray(result.pose, float)
    relocalised = result.loop_correction is not None and stored is not None and not np.array_equal(stored.pose, pose)
    if not relocalised and store.cold_index(s.stream) == pager.cold:
        return
    relocated = pose if relocalised else None
    store.finish_frame(s.stream, seq, relocated, evicted=evicted, restored=pager.pending_restored, **s.pose.fence())
    log_event(
        s.ctx.log,
        "finished the last journaled frame",
        stream=s.stream,
        seq=seq,
        relocalised=relocalised,
        evicted=len(evicted),
        restored=len(pager.pending_restored),
    )
    if relocalised:
        s.pose.publish_pose(seq, stored.stamp, pose, "relocalised", stored.digest, {}, False)
