"""The stream lane's job: one frame of a stream, in sequence order, from its occupancy to its published pose, then its
work after the pose (loop closure, map update, snapshot schedule) in the stream's after-pose thread."""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
import zenoh

from occvo_core.errors import InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.free_cores import FREE_CORES
from occvo_core.grid import OCC3D_GRID
from occvo_core.registration.kernels import use_threads
from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import OccupancyFrameMsg, PoseEstimate
from occvo_services.os_tuning import name_os_thread, run_delay_ms
from occvo_services.registration.state import StreamState
from occvo_services.store_blobs import frame_digest, legacy_frame_digest, pack_frame
from occvo_services.telemetry import log_event

CORES = len(FREE_CORES.cpus)  # the cores this process may run on
_STATUS = {"ok": "ok", "lost": "lost", "initialised": "reinitialised", "reinitialised": "reinitialised"}


def _map_thread_start() -> None:
    """The map thread keeps the lane's priority; its kernels run on one thread (AfterPose._background_thread)."""
    name_os_thread()
    use_threads(1)


class StreamLanes:
    """RegistrationWorker's lanes: sequence checks, registration, pose publishing."""

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
        st.head_start.set()
        if st.tail is not None:
            st.tail.result()
        self._flush_map(stream, st)
        self._map_done(st)
        if st.after_pose is not None:
            st.after_pose.shutdown(wait=True)
            st.after_pose, st.tail = None, None
        if st.map_thread is not None:
            st.map_thread.shutdown(wait=True)
            st.map_thread, st.map_tail = None, None
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

    def _map_done(self, st: StreamState) -> None:
        """Wait until the stream's last tiles are cut and sent (before st.tiles and the tile digests are reset)."""
        if st.map_tail is not None:
            st.map_tail.result()

    def _queued(self, stream: str) -> bool:
        """Whether frames of the stream wait in its lane's queue."""
        lane = self.lanes.get(stream)
        return lane is not None and lane.queue.q.qsize() > 0

    def _fair_threads(self) -> int:
        """Kernel threads for a frame about to be registered: the cores other processes (other shards among them)
        leave free, divided among this worker's lanes busy now (this one included), so one stream alone uses every
        free core and several streams do not oversubscribe them."""
        busy = sum(1 for lane in list(self.lanes.values()) if lane.busy)
        return max(1, FREE_CORES.threads(CORES) // max(1, busy))

    def _kernels(self, vo, waited: list[float] | None, fn, *args):
        """fn(*args) (OccVO.register or complete) in the worker's kernel team thread when vo may use several
        kernel threads, else in the calling thread; adds the team thread's wait for a core to waited[0]."""
        if vo.threads == 1:
            return fn(*args)

        def call():
            w0 = run_delay_ms()
            self._idle_team.restore()  # kernels follow: the team's threads back to the lanes' priority
            try:
                return fn(*args)
            finally:
                if waited is not None:
                    waited[0] += run_delay_ms() - w0

        return self._team.submit(call).result()

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
        """One frame of the stream (_register_frame); counts it as entered, so the last frame's work after its pose
        sees that another came (its map update can wait for this one's)."""
        st = self.state(stream)
        st.entered += 1
        st.head_start.set()  # the last pose's work after it starts now if it still waits
        tail = st.tail
        try:
            self._register_frame(stream, st, item, st.entered)
        finally:
            if st.tail is tail and st.after_pose is not None and not self._queued(stream):
                # no work after a pose followed (refused, a resend) and no frame waits: the tiles held back for it go
                # now (the job runs after the last frame's work, which may hold some back yet)
                st.tail = st.after_pose.submit(self._flush_map, stream, st)

    def _register_frame(self, stream: str, st: StreamState, item, entered: int) -> None:
        msg, hop_ms, t_queued, decode_ms = item
        t0, waited0 = time.perf_counter(), run_delay_ms()
        # what needs nothing of the stream's state runs while the last frame's work after its pose may still run:
        # building and validating the frame, and its digest
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
        tables = msg.occupancy.index_tables(OCC3D_GRID)  # the compact form it came in: digested and journaled as is
        digest = frame_digest(frame.points, frame.labels, msg.stamp, tables)
        t_wait = time.perf_counter()
        if st.tail is not None:  # the previous frame's work after its pose: the odometry is that work's until it ends
            if not st.tail.done():
                self._boost_tail(st)
            st.tail.result()
        t_valid = time.perf_counter()
        timings = dict(msg.timings_ms)
        timings.update(
            {
                "occupancy_hop": hop_ms,
                "decode": decode_ms,
                "registration_queue": (t0 - t_queued) * 1000.0,
                "validate": (t_wait - t0) * 1000.0,
                "after_pose_wait": (t_valid - t_wait) * 1000.0,  # the last frame's work after its pose, still running
            }
        )
        known = st.stored(msg.seq)
        if known is not None and (
            known.digest == digest or known.digest == legacy_frame_digest(frame.points, frame.labels, msg.stamp)
        ):  # a resend (of a store from before the compact digest, too): answer it, register nothing twice
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
            self._map_done(st)
            st.vo = st.vo or self._OccVO(self.occvo_config, threads=self.config.kernel_threads)
            st.vo.reset()
            st.cold, st.cold_digest, st.pending_restored, st.tiles, st.restored_for_next = {}, {}, [], {}, []
            st.since_snapshot, st.send_all_tiles, st.ego_xy, st.snapshot_since = 0, False, None, time.monotonic()
        if self.config.kernel_threads == 0:
            st.vo.threads = self._fair_threads()
        team_wait = [0.0]  # ms the kernel team thread waited for a core for this frame
        t_reg = time.perf_counter()
        backlog = self._queued(stream)
        if st.after_pose is None:
            st.after_pose = ThreadPoolExecutor(1, f"after-{stream}", initializer=self._background_thread)
        if st.map_thread is None:  # started from here: a thread starts at the niceness of the thread that made it
            st.map_thread = ThreadPoolExecutor(1, f"map-{stream}", initializer=_map_thread_start)
            st.map_tail = st.map_thread.submit(int)
        pose_out: Future = Future()
        done: dict = {}  # the registration once it ended: reg, pose_m, status, reg_ms
        submitted: list[Future] = []

        def register() -> None:
            """Preprocess and registration through fine GICP in one call on the stream's cores, also with frames
            waiting (their map updates are coalesced, map_coalesce_s, which leaves the second core little else)."""
            reg = st.vo.register(frame)
            reg_ms = (time.perf_counter() - t_reg) * 1000.0 - reg.timings_ms.get("preprocess", 0.0)
            done.update(reg=reg, pose_m=np.asarray(reg.pose, float), status=_STATUS.get(reg.status, "ok"))
            done.update(reg_ms=reg_ms, reg_timings=reg.timings_ms)  # now: complete() adds its stages to the same watch
            st.tail_running = True

        def after_pose(head_start: bool = False) -> None:
            """This frame's work after its pose (loop closure, the map update, eviction, the next frame's restores) in
            the stream's after-pose thread below the lanes' priority, submitted once (the first of the calls below);
            it stores and publishes nothing before the pose is out (pose_out). head_start: it waits up to
            pose_head_start_ms or until the stream's next frame comes."""
            if not submitted:
                if head_start:
                    st.head_start.clear()
                submitted.append(
                    st.after_pose.submit(
                        self._after_pose,
                        stream,
                        st,
                        msg,
                        done["reg"],
                        frame,
                        digest,
                        done["pose_m"],
                        restart,
                        t_valid,
                        pose_out,
                        entered,
                        head_start=head_start,
                    )
                )
                st.tail = submitted[0]

        def commit_and_publish(lane_wait: float) -> Exception | None:
            """The pose stored, then published; a store failure is returned (nothing published), not raised.
            lane_wait: ms this frame waited for a core so far, other than in the kernel team's thread."""
            w0, t_store = run_delay_ms(), time.perf_counter()
            pose_m, status = done["pose_m"], done["status"]
            phases = {}
            if self.store is not None:
                try:
                    phases = self.store.commit_frame(
                        stream,
                        msg.seq,
                        msg.stamp,
                        digest,
                        status,
                        pose_m,
                        pack_frame(frame, tables),
                        new_trajectory=restart,
                    )
                except Exception as exc:  # noqa: BLE001 - e.g. disk full: publish nothing the store lacks
                    return exc
            timings["registration"] = done["reg_ms"]
            if self.store is not None:  # where a slow commit waited: this worker's writers, another process, the sync
                store_ms = (time.perf_counter() - t_store) * 1000.0
                timings.update(store_commit=store_ms, **{f"store_commit.{k}": v for k, v in phases.items()})
            timings.update({f"registration.{k}": float(v) for k, v in done["reg_timings"].items()})
            # of the above, runnable but without a core (the lane and the kernel team's thread)
            timings["core_wait"] = lane_wait + team_wait[0] + run_delay_ms() - w0
            # before the pose goes out: whoever has the pose and waits for st.tail waits for this. Caught up, it lets
            # the pose through the router to its client first: beside the map update's kernels on both cores the
            # pose's hops each waited for a core
            after_pose(head_start=self.config.pose_head_start_ms > 0)
            self._publish_pose(stream, st, msg.seq, msg.stamp, pose_m, status, digest, timings, restart)
            return None

        def register_commit_and_publish(lane_wait: float) -> Exception | None:
            """A caught-up frame's way to its pose in one thread; lane_wait: the lane's wait for a core before it."""
            w_call = run_delay_ms()
            register()
            if st.vo.threads > 1:  # in the kernel team's thread: its OpenMP threads, spinning, make way for the pose
                self._idle_team.lower(st.vo.threads)
            return commit_and_publish(lane_wait + run_delay_ms() - w_call)

        try:
            try:
                if backlog:  # the work after the pose starts now, beside the commit (the next frame waits for it)
                    self._kernels(st.vo, team_wait, register)
                    after_pose()
                    failed = commit_and_publish(run_delay_ms() - waited0)
                else:
                    # caught up, registration, the commit and the publication are one call in the kernel team's
                    # thread, still on its core: a lane woken between them waited behind the team's spinning OpenMP
                    # thread (1.2 ms of a pose's latency at 2 Hz); the work after the pose waits until it is out
                    # (its kernels on both cores would slow the commit)
                    failed = self._kernels(st.vo, None, register_commit_and_publish, run_delay_ms() - waited0)
            except InvalidFrameError as exc:  # from register(): nothing registered, nothing to do after it
                if restart and self.store is not None:
                    st.vo = None  # reset for nothing: the stored trajectory stands and resumes at the next frame
                self.report_error(
                    stream, "invalid_frame", f"seq {msg.seq}: {exc.reason}", keys.occupancy(stream), msg.seq
                )
                return
            if failed is not None:
                pose_out.set_result(False)
                after_pose()
                st.tail.result()  # its OccVO.complete: then the state goes, rebuilt from the store
                return self._store_failed(stream, st, msg.seq, failed, "not stored, pose not published")
            if restart:
                log_event(self.log, "trajectory started", stream=stream, seq=msg.seq)
                if self.store is not None:
                    self._snapshots.put(lambda: self.store.drop_old_snapshots(stream))
            pose_out.set_result(True)
        finally:
            if "reg" in done:  # registered: its work after the pose runs whatever happened since
                if not pose_out.done():  # the pose did not go out: its work after it stores and publishes nothing
                    pose_out.set_result(False)
                after_pose()
        self.stats.observe("registration", done["reg_ms"])
        for stage in ("validate", "after_pose_wait", "core_wait"):
            self.stats.observe(stage, timings[stage])
        self.stats.observe("occupancy_hop", hop_ms)
        if self.store is not None:
            self.stats.observe("store_commit", timings["store_commit"])

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
        t_encode = time.perf_counter()
        data = encode(pose)
        self.stats.observe("pose_encode", (time.perf_counter() - t_encode) * 1000.0)
        # counted first: a client holding the pose (another thread may wake it before put returns) finds it counted
        self.stats.inc("relocalised" if status == "relocalised" else "frames_out")
        self.session.put(keys.pose(stream), data, congestion_control=zenoh.CongestionControl.BLOCK)
