"""Registration worker: occupancy frames in, OccVO per stream, poses out in sequence order, map tile updates out.

Map updates: after each frame the worker cuts again the map tiles the frame changed (OccVO.pop_changed_region,
occvo_core.map_tiles.retile_region) and publishes only the tiles whose content changed (a tile that emptied is sent
empty), so the map service always equals the odometry's map; the cost follows the changed area, not the map's size.

A frame's pose goes out as soon as it is registered (OccVO.register: through fine GICP); the loop-closure search, the
map update, eviction and restores follow off its latency (OccVO.complete and _finish). A frame that closed a loop
then publishes its relocalised pose (status "relocalised"), which replaces the first.

Durable state (`store_path`, services/store.py): every pose is committed with its frame before it is published, the
OccVO state is snapshotted every `snapshot_every` frames (less often when snapshots would take more than
`snapshot_max_share` of the stream's time) and at shutdown; a restarted worker resumes a stream at its
next frame from the snapshot plus the journaled frames. The lane only copies the state; one writer thread writes the
copies into the store's snapshot file, so neither this stream's next frame nor another stream's commit waits for it.
A resent frame already registered gets its stored pose again.
With `working_radius_m`, map tiles wholly farther than that from the ego leave the working set for the store (the map
service keeps serving them) and come back when the ego is within working_radius_m - tile_m of them.
"""

from __future__ import annotations

import hashlib
import logging
import os
import queue
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import zenoh

from occvo_core.errors import ConfigError, InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.map_tiles import changed_tiles, retile_region
from occvo_core.registration.voxel_map import copied
from occvo_core.working_map import tiles_near, tiles_reached
from schemas import keys
from schemas.codec import encode
from schemas.models import Array, MapTile, MapUpdate, OccupancyFrameMsg, PoseEstimate, Trajectory
from services.runtime import (
    Worker,
    WorkerConfig,
    hold_priority,
    log_event,
    lower_priority,
    name_os_thread,
    release_priority,
    trim_heap,
    worker_main,
)
from services.store import StoredPose, TrajectoryStore, frame_digest, pack_frame, unpack_arrays

_STATUS = {"ok": "ok", "lost": "lost", "initialised": "reinitialised", "reinitialised": "reinitialised"}
MIN_SAFE_RADIUS_M = 60.0  # a frame reaches ~57 m (the grid's corners): eviction closer than that changes registration


class StreamState:
    """One stream: its OccVO (None until this process registered or resumed it) and what queries read."""

    def __init__(self):
        self.vo = None
        self.lock = threading.Lock()  # guards the lists and `latest`; only the stream's lane touches vo
        self.seqs: list[int] = []
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.statuses: list[str] = []
        self.digests: list[bytes] = []
        self.position: dict[int, int] = {}  # seq -> index in the lists
        self.latest: PoseEstimate | None = None
        self.tiles: dict = {}  # published tiles of the working map
        self.started = False  # a trajectory exists (in memory or in the store)
        self.cold: dict[tuple[int, int], list[int]] = {}  # evicted tile -> seqs it was evicted at (its store rows)
        self.cold_digest: dict[tuple[int, int], bytes] = {}  # published content of an evicted tile
        self.pending_restored: list[tuple[int, int, int]] = []  # restored, not yet stored (finish_frame)
        self.since_snapshot = 0
        self.snapshot_due = 0.0  # time.monotonic() before which a snapshot would overrun snapshot_max_share
        self.snapshot_idle = threading.Event()  # no snapshot of this stream queued or being written
        self.snapshot_idle.set()
        self.snapshot_retry = False  # the last snapshot failed: take one at the next frame
        self.send_all_tiles = False  # after a resume: the map service may lack the last frames' tiles
        self.tiling_ms = 0.0
        self.restore_ms = self.evict_ms = 0.0  # the last step's working-map restores and evictions
        self.restored_for_next: list[tuple[int, int]] = []  # tiles restored after the last frame, not yet published
        self.ego_xy: np.ndarray | None = None  # x-y of the last registered pose (eviction and restore centre)
        self.after_pose: ThreadPoolExecutor | None = None  # the stream's thread for the work after a pose
        self.tail = None  # Future of the last frame's work after its pose
        self.tail_lock = threading.Lock()  # orders the lane's priority boost against the end of that work
        self.tail_running = False
        self.tail_tid: int | None = None  # native id of the after-pose thread
        self.tail_boosted = False  # that thread runs at the lane's priority (the lane waits for it)

    def append(self, seq: int, stamp: float, pose: np.ndarray, status: str, digest: bytes) -> None:
        self.position[seq] = len(self.seqs)
        self.seqs.append(seq)
        self.stamps.append(stamp)
        self.poses.append(pose)
        self.statuses.append(status)
        self.digests.append(digest)

    def clear(self) -> None:
        self.seqs, self.stamps, self.poses, self.statuses, self.digests, self.position = [], [], [], [], [], {}

    def stored(self, seq: int) -> StoredPose | None:
        i = self.position.get(seq)
        return None if i is None else StoredPose(seq, self.stamps[i], self.digests[i], self.statuses[i], self.poses[i])


def _tile_digest(tile) -> bytes:
    p, l = tile
    return hashlib.blake2b(
        np.ascontiguousarray(p).tobytes() + np.ascontiguousarray(l).tobytes(), digest_size=16
    ).digest()


class RegistrationWorker(Worker):
    """Occupancy frames -> OccVO poses and map tiles."""

    role = "registration"

    def __init__(self, config: WorkerConfig):
        super().__init__(config)
        from occvo_core import OccVO, OccVOConfig

        self._OccVO = OccVO
        self.occvo_config = OccVOConfig.load(config.occvo_config) if config.occvo_config else OccVOConfig()
        self.states: dict[str, StreamState] = {}
        self._states_lock = threading.Lock()
        radius = config.working_radius_m
        self.evict_off = radius is not None and config.store_path is None
        if self.evict_off:  # the deploy config sets a radius; eviction starts when a store is given
            self.config = config = config.model_copy(update={"working_radius_m": None})
            radius = None
        if radius is not None and radius <= config.tile_m:
            raise ConfigError(
                f"working_radius_m ({radius}) must exceed tile_m ({config.tile_m}): tiles come back "
                "within working_radius_m - tile_m"
            )
        self.store = TrajectoryStore(config.store_path, config.store_sync.upper()) if config.store_path else None
        self._snapshots: queue.Queue = queue.Queue()
        self._boost_refused = False
        self._snapshot_writer = None
        if self.store is not None:
            self._snapshot_writer = threading.Thread(target=self._write_snapshots, name="snapshot-writer", daemon=True)
            self._snapshot_writer.start()
            for stream in filter(self.owns, self.store.streams()):  # queries answer at once; resumed at the next frame
                st = self.states[stream] = StreamState()
                for p in self.store.poses(stream):
                    st.append(p.seq, p.stamp, p.pose, p.status, p.digest)
                st.started = bool(st.seqs)
                if st.started:
                    st.latest = self._pose_msg(stream, st.stored(st.seqs[-1]))
        if config.warm_up:  # before the worker is announced: no kernel compiles while frames wait (occvo_core.warm_up)
            from occvo_core.warm_up import warm_up

            log_event(self.log, "kernels ready", **warm_up(self.occvo_config, config.kernel_threads))
            trim_heap()

    def owns(self, stream: str) -> bool:
        """This worker's shard registers the stream (a malformed stream id is shard 0's to report)."""
        c = self.config
        return keys.shard_of(stream, c.shards) == c.shard if keys.STREAM_RE.match(stream) else c.shard == 0

    def declare(self) -> None:
        s = self.session
        self._declared += [
            s.declare_subscriber(keys.occupancy("*"), self._on_occupancy),
            s.declare_queryable(keys.pose_latest("*"), self._on_pose_latest),
            s.declare_queryable(keys.trajectory("*"), self._on_trajectory),
        ]
        # clients watch their shard's token: frames sent while their stream's worker is away are resent when it is back
        self._declared.append(
            s.liveliness().declare_token(keys.registration_shard(self.config.shard, self.config.shards, self.worker_id))
        )
        if self.evict_off:
            log_event(self.log, "working_radius_m ignored: eviction needs store_path (the evicted map goes there)")
        if self.store is not None:
            log_event(
                self.log,
                "trajectory store",
                path=self.config.store_path,
                streams=sorted(self.states),
                working_radius_m=self.config.working_radius_m,
                snapshot_every=self.config.snapshot_every,
            )
            if self.config.working_radius_m is not None and self.config.working_radius_m < MIN_SAFE_RADIUS_M:
                log_event(
                    self.log,
                    "working radius below a frame's reach: eviction changes registration",
                    working_radius_m=self.config.working_radius_m,
                )

    def after_leaving(self) -> None:
        """Off the network (the frames in hand finished): end the streams' after-pose threads, then snapshot every
        stream with unsnapshotted frames."""
        for stream, st in list(self.states.items()):
            lane = self.lanes.get(stream)
            if st.after_pose is not None and not (lane is not None and lane.thread.is_alive()):
                st.after_pose.shutdown(wait=True)  # drained already: its thread ends now, not at interpreter exit
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

    def state(self, stream: str) -> StreamState:
        with self._states_lock:
            if stream not in self.states:
                self.states[stream] = StreamState()
            return self.states[stream]

    def retire_stream(self, stream: str) -> None:
        """An idle stream: its after-pose thread ends; with a store its OccVO is snapshotted and dropped (the next
        frame resumes it from the store), without one it stays in memory (it is the only copy)."""
        st = self.states.get(stream)
        if st is None:
            return
        if st.tail is not None:
            st.tail.result()
        if st.after_pose is not None:
            st.after_pose.shutdown(wait=True)
            st.after_pose, st.tail = None, None
        if self.store is None or st.vo is None:
            return
        st.snapshot_idle.wait()
        if st.since_snapshot > 0 or st.snapshot_retry:
            st.snapshot_idle.clear()
            self._write_snapshot(stream, st, st.seqs[-1], self.store.created(stream), st.vo.state_dict(copy=False))
        st.vo, st.tiles, st.cold, st.cold_digest, st.restored_for_next = (
            None,
            {},
            {},
            {},
            [],
        )  # heap trimmed by the caller

    def check_seq(self, stream: str, seq: int, key: str) -> bool:
        return True  # judged in the lane against the stream's trajectory: a step back may be a resend

    def _on_occupancy(self, sample: zenoh.Sample) -> None:
        if self.owns(keys.stream_of(str(sample.key_expr))):  # another shard's stream: not ours to count or judge
            self.enqueue(sample, OccupancyFrameMsg, self._register)

    def _seq_error(self, stream: str, code: str, message: str, seq: int) -> None:
        self.stats.inc(code)
        self.report_error(stream, code, message, keys.occupancy(stream), seq)

    # -- one frame ------------------------------------------------------------------------------------------------
    def _register(self, stream: str, item) -> None:
        msg, hop_ms, t_queued = item
        st = self.state(stream)
        if st.tail is not None:  # the previous frame's work after its pose: the odometry is that work's until it ends
            if not st.tail.done():
                self._boost_tail(st)
            st.tail.result()
        t0 = time.perf_counter()
        frame = OccupancyFrame(
            msg.occupancy.to_points(),
            msg.occupancy.labels.to_numpy().copy(),
            index=msg.seq,
            stamp=msg.stamp,
            meta={"stream": stream, "source": msg.source},
        )
        try:
            frame.validate()  # before any reset, so a bad first frame leaves the old trajectory and map intact
        except InvalidFrameError as exc:
            self.report_error(stream, "invalid_frame", f"seq {msg.seq}: {exc.reason}", keys.occupancy(stream), msg.seq)
            return
        digest = frame_digest(frame.points, frame.labels, msg.stamp)
        known = st.stored(msg.seq)
        if known is not None and known.digest == digest:  # a resend: answer it, register nothing twice
            self.stats.inc("republished")
            self.session.put(
                keys.pose(stream),
                encode(self._pose_msg(stream, known)),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            return
        restart = msg.seq == 0 or not st.started
        if not restart:
            last = st.seqs[-1]
            if msg.seq <= last:
                what = "differs from the registered frame" if known is not None else "is older than the trajectory"
                return self._seq_error(
                    stream, "out_of_order", f"seq {msg.seq} arrived after seq {last} and {what}; dropped", msg.seq
                )
            if msg.seq - last > self.config.max_seq_jump:  # adopted, one stray seq would make every real frame old
                return self._seq_error(
                    stream,
                    "seq_jump",
                    f"seq {msg.seq} is {msg.seq - last} after seq {last}, beyond "
                    f"the window of {self.config.max_seq_jump}; dropped",
                    msg.seq,
                )
            if msg.seq > last + 1:
                self._seq_error(
                    stream,
                    "missing_seq",
                    f"missing seq {last + 1}..{msg.seq - 1} ({msg.seq - last - 1} frames) before seq {msg.seq}",
                    msg.seq,
                )
            if st.vo is None:
                self._resume(stream, st)
        if restart:  # only this lane's thread touches st.vo; queries read the lists under st.lock
            st.vo = st.vo or self._OccVO(self.occvo_config, threads=self.config.kernel_threads)
            st.vo.reset()
            st.cold, st.cold_digest, st.pending_restored, st.tiles, st.restored_for_next = {}, {}, [], {}, []
            st.since_snapshot, st.send_all_tiles, st.ego_xy = 0, False, None
        try:
            reg = st.vo.register(frame)
        except InvalidFrameError as exc:
            if restart and self.store is not None:
                st.vo = None  # reset for nothing: the stored trajectory stands and resumes at the next frame
            self.report_error(stream, "invalid_frame", f"seq {msg.seq}: {exc.reason}", keys.occupancy(stream), msg.seq)
            return
        reg_ms = (time.perf_counter() - t0) * 1000.0
        pose_m = np.asarray(reg.pose, float)
        status = _STATUS.get(reg.status, "ok")
        t_store = time.perf_counter()
        phases = {}
        if self.store is not None:
            try:
                phases = self.store.commit_frame(
                    stream, msg.seq, msg.stamp, digest, status, pose_m, pack_frame(frame), new_trajectory=restart
                )
            except Exception as exc:  # noqa: BLE001 - e.g. disk full: publish nothing the store lacks; rebuild from it
                return self._store_failed(stream, st, msg.seq, exc, "not stored, pose not published")
        store_ms = (time.perf_counter() - t_store) * 1000.0
        timings = dict(msg.timings_ms)
        timings.update(
            {"occupancy_hop": hop_ms, "registration_queue": (t0 - t_queued) * 1000.0, "registration": reg_ms}
        )
        if self.store is not None:  # with where a slow commit waited: this worker's writers, another process, the sync
            timings.update(store_commit=store_ms, **{f"store_commit.{k}": v for k, v in phases.items()})
        timings.update({f"registration.{k}": float(v) for k, v in reg.timings_ms.items()})
        self._publish_pose(stream, st, msg.seq, msg.stamp, pose_m, status, digest, timings, restart)
        self.stats.observe("registration", reg_ms)
        self.stats.observe("occupancy_hop", hop_ms)
        if self.store is not None:
            self.stats.observe("store_commit", store_ms)
        if restart:
            log_event(self.log, "trajectory started", stream=stream, seq=msg.seq)
            if self.store is not None:
                self._snapshots.put(lambda: self.store.drop_old_snapshots(stream))
        # the pose is out: loop closure, the map update, eviction and the next frame's restores run off its latency,
        # in the stream's after-pose thread, below the lanes' priority (other streams' poses go first on the cores)
        if st.after_pose is None:
            st.after_pose = ThreadPoolExecutor(1, f"after-{stream}", initializer=self._background_thread)
        st.tail_running = True
        st.tail = st.after_pose.submit(self._after_pose, stream, st, msg, reg, frame, digest, pose_m, restart, t0)

    def _after_pose(
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
    ) -> None:
        """A frame's work after its pose: OccVO.complete and _finish, their second store write, a relocalised pose,
        the map update and the snapshot schedule. A failure is reported as a lane reports one."""
        st.tail_tid = threading.get_native_id()
        try:
            self._after_pose_steps(stream, st, msg, reg, frame, digest, pose_m, restart, t0)
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
        """Start of a thread doing work off the poses' path: after_pose_nice below the lanes."""
        name_os_thread()
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
    ) -> None:
        t_tail = time.perf_counter()
        result, restored, evicted, (tiles, dirty) = self._finish(stream, st, reg, frame, msg.seq, publish=True)
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
        t_map = time.perf_counter()
        sent = self._publish_map(stream, st, msg.seq, restart, tiles, dirty, evicted, restored)
        t_end = time.perf_counter()
        map_ms = (t_end - t_map) * 1000.0 + st.tiling_ms
        self.stats.observe("map_update", map_ms)
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
                tiling_ms=round(st.tiling_ms, 1),
                restore_ms=round(st.restore_ms, 1),
                evict_ms=round(st.evict_ms, 1),
                store_ms=round((t_map - t_finished) * 1000.0),
                publish_map_ms=round((t_end - t_map) * 1000.0),
                tiles_sent=sent[0],
                map_update_bytes=sent[1],
                relocalised=relocalised,
            )
        self.stats.observe("stage_total", (time.perf_counter() - t0) * 1000.0)
        if self.store is not None:
            st.since_snapshot += 1
            due = st.snapshot_retry or (
                st.since_snapshot >= self.config.snapshot_every and time.monotonic() >= st.snapshot_due
            )
            if due and st.snapshot_idle.is_set():
                self._queue_snapshot(stream, st)

    def _publish_pose(
        self,
        stream: str,
        st: StreamState,
        seq: int,
        stamp: float,
        pose_m: np.ndarray,
        status: str,
        digest: bytes,
        timings: dict,
        restart: bool,
    ) -> None:
        """Record the pose for queries and publish it; a relocalised pose replaces the one of its seq."""
        pose = PoseEstimate(
            stream=stream,
            seq=seq,
            stamp=stamp,
            pose=pose_m.tolist(),
            status=status,
            timings_ms=timings,
            sent_at=time.time(),
        )
        with st.lock:
            if restart:
                st.clear()
                st.started = True
            if seq in st.position:
                i = st.position[seq]
                st.poses[i], st.statuses[i] = pose_m, status
            else:
                st.append(seq, stamp, pose_m, status, digest)
            st.latest = pose
        data = encode(pose)
        # counted first: a client holding the pose (another thread may wake it before put returns) finds it counted
        self.stats.inc("relocalised" if status == "relocalised" else "frames_out")
        self.session.put(keys.pose(stream), data, congestion_control=zenoh.CongestionControl.BLOCK)

    def _store_failed(self, stream: str, st: StreamState, seq: int, exc: Exception, what: str) -> None:
        """A write failed (e.g. disk full): drop the in-memory state; the stream resumes from the store at its next
        frame (replaying the journal redoes what was not stored)."""
        st.vo = None
        st.tiles = {}
        self.report_error(
            stream,
            "internal",
            f"seq {seq} {what} ({type(exc).__name__}: {exc}); the stream resumes from the store at its next frame",
            keys.occupancy(stream),
            seq,
        )

    # -- durable state --------------------------------------------------------------------------------------------
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
            if self.config.snapshot_max_share is not None:
                st.snapshot_due = time.monotonic() + took / self.config.snapshot_max_share
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
            if st.tail is not None:
                st.tail.result()

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
            result, restored, evicted, (tiles, dirty) = self._advance(stream, st, frame, seq, publish=last)
            if last:  # it may have stopped before its map update was stored or published: do both again
                self._finish_last(stream, st, seq, result, evicted)
                self._publish_map(stream, st, seq, False, tiles, dirty, evicted, restored)
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
        st.since_snapshot = len(journal)
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

    # -- one step and the bounded working map ----------------------------------------------------------------------
    def _advance(self, stream: str, st: StreamState, frame: OccupancyFrame, seq: int, publish: bool):
        """A whole frame as a live one goes (register, then _finish); a resume's replay of the journal uses it, so it
        reproduces the poses."""
        return self._finish(stream, st, st.vo.register(frame), frame, seq, publish)

    def _finish(self, stream: str, st: StreamState, reg, frame: OccupancyFrame, seq: int, publish: bool):
        """After the pose: loop closure and map update (OccVO.complete), keep every tile wholly resident or wholly
        cold, evict far map, and bring back the cold map near the new pose, which the next frame registers against.
        Returns (result, tiles restored, evicted blocks, tiles of the working map before eviction if publish)."""
        result = st.vo.complete(reg)
        pose = np.asarray(result.pose, float)
        t0 = time.perf_counter()
        restored = list(st.restored_for_next)
        if st.cold:  # a frame that reached into an evicted tile: bring the rest back, so the tile stays whole
            restored += self._restore(stream, st, self._reached(st, frame, pose))
        t_map = time.perf_counter()
        tiles = dirty = None
        if publish:  # only the part of the map this frame changed is cut again (a replay leaves the region open)
            tiles, dirty = retile_region(st.tiles, st.vo.map_points, st.vo.pop_changed_region(), self.config.tile_m)
        st.tiling_ms = (time.perf_counter() - t_map) * 1000.0
        t_evict = time.perf_counter()
        evicted = self._evict_far(st, seq, pose)
        st.evict_ms = (time.perf_counter() - t_evict) * 1000.0
        st.ego_xy = pose[:2, 3].copy()
        t_near = time.perf_counter()
        # published with the next frame's tiles (they are cut then); committed with this frame
        st.restored_for_next = self._restore(stream, st, self._near(st))
        st.restore_ms = (t_map - t0 + time.perf_counter() - t_near) * 1000.0
        return result, restored, evicted, (tiles, dirty)

    def _reached(self, st: StreamState, frame: OccupancyFrame, pose: np.ndarray) -> list[tuple[int, int]]:
        """Cold tiles the frame's points reach at `pose` (occvo_core.working_map.tiles_reached)."""
        return tiles_reached(st.cold, frame.points, pose, self.config.tile_m)

    def _near(self, st: StreamState) -> list[tuple[int, int]]:
        """Cold tiles near the last pose to bring back (occvo_core.working_map.tiles_near)."""
        radius = self.config.working_radius_m
        if radius is None or not st.cold:
            return []
        return tiles_near(st.cold, st.ego_xy, radius, self.config.tile_m)

    def _restore(self, stream: str, st: StreamState, back: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """Put cold tiles back into the working map (newest block first: put() keeps a cell's newer voxel)."""
        for k in back:
            seqs = st.cold.pop(k)
            for e in sorted(seqs, reverse=True):
                st.vo.restore_tiles({k: unpack_arrays(self.store.cold_block(stream, k[0], k[1], e))})
                st.pending_restored.append((k[0], k[1], e))
        if back:
            self.stats.inc("tiles_restored", len(back))
        return list(back)

    def _evict_far(self, st: StreamState, seq: int, pose: np.ndarray) -> dict:
        """After a step: take the tiles wholly farther than working_radius_m out of the working map."""
        if self.config.working_radius_m is None:
            return {}
        blocks = st.vo.evict_tiles(pose[:2, 3], self.config.working_radius_m, self.config.tile_m)
        for k in blocks:
            st.cold.setdefault(k, []).append(seq)
        if blocks:
            self.stats.inc("tiles_evicted", len(blocks))
        return blocks

    def _publish_map(
        self,
        stream: str,
        st: StreamState,
        seq: int,
        restart: bool,
        tiles: dict,
        dirty: set,
        evicted: dict,
        restored: list,
    ) -> None:
        """Changed tiles of the working map as it was before this frame's eviction (an evicted tile goes out with its
        last content, then is not sent as emptied: the map service keeps it); a restored tile only if it changed."""
        if restart or st.send_all_tiles:
            changed = dict(tiles)
        else:
            changed = changed_tiles(
                {k: st.tiles[k] for k in dirty if k in st.tiles}, {k: tiles[k] for k in dirty if k in tiles}
            )
            for k in restored:
                was = st.cold_digest.pop(k, None)
                if k in changed and was is not None and _tile_digest(changed[k]) == was:
                    del changed[k]
        for k in evicted:
            if k in tiles:
                st.cold_digest[k] = _tile_digest(tiles[k])
        st.send_all_tiles = False
        st.tiles = {k: v for k, v in tiles.items() if k not in evicted} if evicted else tiles
        tile_m = self.config.tile_m
        update = MapUpdate(
            stream=stream,
            seq=seq,
            reset=restart,
            tile_m=tile_m,
            tiles=[
                MapTile(
                    stream=stream,
                    ix=ix,
                    iy=iy,
                    tile_m=tile_m,
                    seq=seq,
                    points=Array.from_numpy(np.asarray(p, np.float64)),
                    labels=Array.from_numpy(np.asarray(l, np.uint8)),
                )
                for (ix, iy), (p, l) in sorted(changed.items())
            ],
        )
        return len(update.tiles), self._put_update(stream, update)

    def _put_update(self, stream: str, update: MapUpdate) -> int:
        """Publish a map update; one over max_message_bytes goes as several (the transport drops bigger messages),
        the reset with the first. Returns the bytes sent."""
        data = encode(update, 1 << 30)
        if len(data) > self.config.max_message_bytes and len(update.tiles) > 1:
            half = len(update.tiles) // 2
            return self._put_update(
                stream, update.model_copy(update={"tiles": update.tiles[:half]})
            ) + self._put_update(stream, update.model_copy(update={"tiles": update.tiles[half:], "reset": False}))
        self.session.put(keys.map_updates(stream), data, congestion_control=zenoh.CongestionControl.BLOCK)
        return len(data)

    # -- queries --------------------------------------------------------------------------------------------------
    @staticmethod
    def _pose_msg(stream: str, p: StoredPose) -> PoseEstimate:
        return PoseEstimate(
            stream=stream,
            seq=p.seq,
            stamp=p.stamp,
            pose=np.asarray(p.pose, float).tolist(),
            status=p.status,
            timings_ms={},
            sent_at=time.time(),
        )

    def _matching(self, query: zenoh.Query, key_of) -> list[tuple[str, StreamState]]:
        q = query.key_expr
        with self._states_lock:
            items = list(self.states.items())
        found = [
            (s, st)
            for s, st in sorted(items, key=lambda i: i[0])
            if st.started and q.intersects(zenoh.KeyExpr(key_of(s)))
        ]
        return found[: self.config.max_query_streams]  # a wildcard asks for every stream: the first ones answer

    def _on_pose_latest(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.pose_latest)
        if not found:  # one worker answers a miss: the stream's shard's (shard 0's for a wildcard)
            if self.owns(keys.stream_of(str(query.key_expr))):
                self.reply_error(
                    query, keys.stream_of(str(query.key_expr)), "bad_query", f"no poses for {query.key_expr}"
                )
            return
        for s, st in found:
            with st.lock:
                latest = st.latest
            query.reply(keys.pose_latest(s), encode(latest))

    def _on_trajectory(self, query: zenoh.Query) -> None:
        found = self._matching(query, keys.trajectory)
        if not found:  # one worker answers a miss: the stream's shard's (shard 0's for a wildcard)
            if self.owns(keys.stream_of(str(query.key_expr))):
                self.reply_error(
                    query, keys.stream_of(str(query.key_expr)), "bad_query", f"no trajectory for {query.key_expr}"
                )
            return
        for s, st in found:
            with st.lock:
                traj = Trajectory(
                    stream=s,
                    seqs=Array.from_numpy(np.array(st.seqs, np.int64)),
                    stamps=Array.from_numpy(np.array(st.stamps, np.float64)),
                    poses=Array.from_numpy(np.array(st.poses, np.float64).reshape(-1, 4, 4)),
                )
            query.reply(keys.trajectory(s), encode(traj, 1 << 30))


def _args(p) -> None:
    p.add_argument("--shard", type=int, help="register the streams of this shard (0..shards-1)")
    p.add_argument("--shards", type=int, help="registration workers sharing the streams (by a hash of the stream id)")
    p.add_argument("--tile-m", type=float)
    p.add_argument("--occvo-config")
    p.add_argument("--store-path", help="SQLite file of the trajectories, snapshots and evicted map (default: none)")
    p.add_argument("--snapshot-every", type=int, help="frames between state snapshots")
    p.add_argument("--snapshot-max-share", type=float, help="snapshots take at most this share of a stream's time")
    p.add_argument("--working-radius-m", type=float, help="evict map tiles farther than this from the ego to the store")
    p.add_argument(
        "--after-pose-nice", type=int, help="niceness of the work after a pose, relative to the lanes (0: same)"
    )
    p.add_argument("--store-sync", choices=["full", "normal"], help="full: a published pose survives a power cut too")


if __name__ == "__main__":
    sys.exit(worker_main(RegistrationWorker, extra_args=_args))
