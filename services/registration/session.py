"""One stream's session in the registration worker: its OccVO, trajectory, working map and paging, threads and
durability. A frame goes through named phases (docs/service.md has the picture):

    validate -> sequence -> register -> commit -> publish | after-pose (complete, store, map update, snapshot)

The pose is published only after its commit; the work after it runs in the session's after-pose thread."""

from __future__ import annotations

import threading
import time

import numpy as np

from occvo_core.errors import InvalidFrameError
from occvo_schemas import keys
from occvo_schemas.models import PoseEstimate
from occvo_schemas.pose_v1 import pose_puts
from occvo_services.flow import judge_seq
from occvo_services.os_tuning import run_delay_ms
from occvo_services.registration.frame_job import STATUS, FrameJob, SessionContext, frame_job
from occvo_services.registration.map_output import MapOutput
from occvo_services.registration.paging import Pager
from occvo_services.registration.resume import load_snapshot, resume
from occvo_services.registration.scheduling import StreamThreads
from occvo_services.registration.snapshots import SnapshotSchedule
from occvo_services.registration.store_faults import refused, store_back, store_failed, waits_for_refused
from occvo_services.registration.trajectory import StreamTrajectory, pose_message
from occvo_services.store.blobs import legacy_frame_digest, pack_frame
from occvo_services.store.errors import FencedError, StoreUnavailable
from occvo_services.telemetry import log_event


class StreamSession:
    """A stream's state and the phases of its frames; closed (state to the store) and reopened from the store."""

    def __init__(self, stream: str, ctx: SessionContext):
        self.stream, self.ctx = stream, ctx
        c = ctx.config
        self.vo = None  # None until this process registered or resumed the stream
        self.trajectory = StreamTrajectory()
        self.pager = Pager(stream, ctx.store, ctx.stats, c.working_radius_m, c.tile_m)
        self.map = MapOutput(stream, c, ctx.stats, ctx.log, ctx.put, ctx.report_error)
        self.threads = StreamThreads(stream, ctx.scheduler)
        self.snapshot = SnapshotSchedule()
        self.held: FrameJob | None = None  # a jump waiting for the frame after it (_sequence)
        self.unstored: set[int] = set()  # frames refused or turned away (store_faults): the ones after the first wait
        self.refusal_lock = threading.Lock()
        self.entered = 0  # frames that entered the lane: the work after a pose sees whether another came
        self.epoch: int | None = None  # placement "members": the fencing epoch of this worker's lease on the stream
        self.client: str | None = None  # whose frames these are (the worker's admission): the store records it

    def load_trajectory(self) -> None:
        """The stored trajectory, for queries and resends (the OccVO is resumed at the stream's next frame); the one
        in memory stays if the store cannot be read."""
        t = StreamTrajectory()
        for p in self.ctx.store.poses(self.stream):
            t.append(p.seq, p.stamp, p.pose, p.status, p.digest)
        t.started = bool(t.seqs)
        if t.started:
            t.latest = pose_message(self.stream, t.stored(t.last_seq))
        self.trajectory = t

    # -- a frame, phase by phase ------------------------------------------------------------------------------------
    def handle(self, item) -> None:
        """The lane's handler: one frame. Counted as entered, so the last frame's work after its pose sees that
        another came (its map update can wait for this one's)."""
        self.entered += 1
        self.threads.head_start.set()  # the last pose's work after it starts now if it still waits
        tail = self.threads.tail
        try:
            self._frame(item, self.entered)
        finally:
            self.ctx.catch_up.end(self.stream)  # reopened: caught up with its first frame after it
            if self.threads.tail is tail and self.threads.after is not None and not self._queued():
                # no work after a pose followed (refused, a resend) and no frame waits: the tiles held back go now
                self.threads.submit_after(self.flush_map)

    def _frame(self, item, entered: int) -> None:
        msg, hop_ms, t_queued, decode_ms = item[:4]
        t0, waited0 = time.perf_counter(), run_delay_ms()
        job = self._validate(msg, entered)  # needs nothing of the state: beside the last frame's after-pose work
        if job is None or not store_back(self, job.msg.seq):
            return
        t_wait = time.perf_counter()
        self.threads.wait_after_pose()  # the odometry is that work's until it ends
        job.t_valid = time.perf_counter()
        job.timings.update(
            occupancy_hop=hop_ms,
            decode=decode_ms,
            registration_queue=(t0 - t_queued) * 1000.0,
            validate=(t_wait - t0) * 1000.0,
            after_pose_wait=(job.t_valid - t_wait) * 1000.0,  # the last frame's work after its pose, still running
        )
        first = job.msg.seq  # the first frame of this call left unregistered if the store fails under it
        try:
            if not self._own(job) or self._answer_resend(job) or waits_for_refused(self, job):
                return
            held = self._confirmed(job)
            if held is not None:
                first = held.msg.seq
                if self._sequence(held, confirmed=True):
                    if self._register_commit_publish(held, waited0):
                        self._observe_frame(held)
                    self.threads.head_start.set()  # this frame follows at once: the held one's work after its pose
                    self.threads.wait_after_pose()
                first = job.msg.seq
            if self._sequence(job) and self._register_commit_publish(job, waited0):
                self._observe_frame(job)
        except StoreUnavailable as exc:  # reading the stream back (its lease, trajectory, resume) failed
            store_failed(self, first, exc, "not registered")
            refused(self, first)

    def _validate(self, msg, entered: int) -> FrameJob | None:
        """The frame built and checked before any reset (a bad first frame leaves the old trajectory intact)."""
        try:
            return frame_job(msg, self.stream, entered)
        except InvalidFrameError as exc:
            self._report("invalid_frame", f"seq {msg.seq}: {exc.reason}", msg.seq)
            return None

    def _own(self, job: FrameJob) -> bool:
        """Placement "members": the stream's lease held before anything is written here. Taken, the stream is
        reloaded from the store: another worker may have moved it on since this one last had it."""
        leases = self.ctx.leases
        if leases is None or self.epoch is not None:
            return True
        epoch, owner = leases.acquire(self.stream)
        if epoch is None:  # another live worker took it meanwhile: its frames are that worker's (it has them too)
            leases.placement.forget(self.stream)
            log_event(self.ctx.log, "stream taken by another worker", stream=self.stream, owner=owner)
            return False
        self.threads.drain()
        self.vo = None
        self.load_trajectory()  # before the epoch: a read that failed takes the lease again at the next frame
        self.epoch = epoch
        return True

    @property
    def may_write(self) -> bool:
        """Placement "members": only while this worker holds the stream's lease (its epoch)."""
        return self.ctx.leases is None or self.epoch is not None

    def fence(self) -> dict:
        """The keyword a store write of this stream carries: its lease's epoch, checked in the write's transaction.
        Placement "members" without the lease: FencedError, nothing written (every write there is fenced)."""
        if self.ctx.leases is None:
            return {}
        if self.epoch is None:
            raise FencedError(self.stream, None, None)
        return {"epoch": self.epoch}

    def _answer_resend(self, job: FrameJob) -> bool:
        """A frame registered already (a resend, also of a store from before the compact digest): its stored pose
        again, nothing registered twice."""
        known = self.trajectory.stored(job.msg.seq)
        f = job.frame
        if known is None or (
            known.digest != job.digest and known.digest != legacy_frame_digest(f.points, f.labels, job.msg.stamp)
        ):
            return False
        self.ctx.stats.inc("republished")
        for key, data in pose_puts(pose_message(self.stream, known)):
            self.ctx.put(key, data)
        return True

    def _confirmed(self, job: FrameJob) -> FrameJob | None:
        """The held jump this frame confirms (it is the held frame's next seq), else None."""
        held, t = self.held, self.trajectory
        if held is None or job.msg.seq != held.msg.seq + 1 or not t.started or held.msg.seq <= t.last_seq + 1:
            return None
        self.held = None
        return held

    def _sequence(self, job: FrameJob, confirmed: bool = False) -> bool:
        """The frame's place after the committed trajectory (services/flow.judge_seq); then the OccVO it registers
        on: a new one at seq 0, else the stream's, resumed from the store if this process has none. A jump (a seq
        more than one ahead, within max_seq_jump) is held, not adopted, until the frame after it confirms it: one
        stray seq must not make the stream's real next frames steps back (lossless policy; under "latest" frames
        are dropped on purpose and a jump is taken at once)."""
        seq, t = job.msg.seq, self.trajectory
        job.restart = seq == 0 or not t.started
        if not job.restart:
            jump = seq - t.last_seq
            # under the "latest" policy frames are dropped on purpose: a gap there is the normal case, not held
            hold = not confirmed and self.ctx.config.policy == "lossless"
            if hold and 1 < jump <= self.ctx.config.max_seq_jump:
                self.held = job  # a later jump replaces it; the stream's real next frame drops it
                self.ctx.stats.inc("seq_held")
                self._report("seq_held", f"seq {seq} is {jump} after seq {t.last_seq}: held until seq {seq + 1}", seq)
                return False
            if jump == 1:
                self.held = None
            known = t.stored(seq) is not None
            older = " and differs from the registered frame" if known else " and is older than the trajectory"
            ok, code, message = judge_seq(seq, t.last_seq, self.ctx.config.max_seq_jump, older)
            if code is not None:
                self.ctx.stats.inc(code)
                self._report(code, message, seq)
            if not ok:
                return False
            if self.vo is None:
                self.reopen()
        else:
            self.held = None
            self._new_trajectory()
        if self.ctx.config.kernel_threads == 0:
            self.vo.threads = self.ctx.scheduler.fair_threads(self.ctx.busy_lanes())
        return True

    def _register_commit_publish(self, job: FrameJob, waited0: float) -> bool:
        """Register, commit, publish. Caught up, the three are one call in the kernel team's thread (a lane woken
        between them waited behind the team's spinning OpenMP threads) and the work after the pose waits until it
        is out; with frames waiting, that work starts as soon as the frame is registered. True: the pose is out."""
        self.ctx.catch_up.wait_turn(self.stream)
        job.t_reg = time.perf_counter()
        backlog = self._queued()
        self.threads.start()
        team = self.ctx.scheduler
        try:
            try:
                if backlog:
                    _, team_wait = team.kernels(self.vo, self._register, job)
                    self._submit_after_pose(job)
                    failed = self._commit_and_publish(job, run_delay_ms() - waited0 + team_wait)
                else:
                    failed, _ = team.kernels(self.vo, self._caught_up, job, run_delay_ms() - waited0)
            except InvalidFrameError as exc:  # from register: nothing registered, nothing to do after it
                if job.restart and self.ctx.store is not None:
                    self.vo = None  # reset for nothing: the stored trajectory stands and resumes at the next frame
                self._report("invalid_frame", f"seq {job.msg.seq}: {exc.reason}", job.msg.seq)
                return False
            if failed is not None:
                job.pose_out.set_result(False)
                self._submit_after_pose(job)
                job.after.result()  # its OccVO.complete: then the state goes, rebuilt from the store
                store_failed(self, job.msg.seq, failed, "not stored, pose not published")
                if not isinstance(failed, FencedError):
                    refused(self, job.msg.seq)
                return False
            if job.restart:
                log_event(self.ctx.log, "trajectory started", stream=self.stream, seq=job.msg.seq)
                if self.ctx.store is not None:
                    self.ctx.snapshots.forget_old(self.stream)
            job.pose_out.set_result(True)
            return True
        finally:
            if job.reg is not None:  # registered: its work after the pose runs whatever happened since
                if not job.pose_out.done():  # the pose did not go out: that work stores and publishes nothing
                    job.pose_out.set_result(False)
                self._submit_after_pose(job)

    def _caught_up(self, job: FrameJob, lane_wait: float) -> Exception | None:
        """A caught-up frame's way to its pose in one thread; lane_wait: the lane's wait for a core before it."""
        w_call = run_delay_ms()
        self._register(job)
        self.ctx.scheduler.kernels_done(self.vo.threads)
        return self._commit_and_publish(job, lane_wait + run_delay_ms() - w_call)

    def _register(self, job: FrameJob) -> None:
        """Preprocess and registration through fine GICP (OccVO.register): the pose, nothing changed yet."""
        reg = self.vo.register(job.frame)
        job.reg_timings = dict(reg.timings_ms)  # complete() adds its stages to the same stopwatch later
        job.reg_ms = (time.perf_counter() - job.t_reg) * 1000.0  # its stages (registration.<stage>) included
        job.reg, job.pose_m, job.status = reg, np.asarray(reg.pose, float), STATUS.get(reg.status, "ok")
        self.threads.work_due()

    def _commit_and_publish(self, job: FrameJob, wait_ms: float) -> Exception | None:
        """The pose stored, then published; a store failure is returned (nothing published), not raised.
        wait_ms: this frame's wait for a core so far."""
        w0, t_store = run_delay_ms(), time.perf_counter()
        store, msg, timings = self.ctx.store, job.msg, job.timings
        if store is not None:
            try:
                phases = store.commit_frame(
                    self.stream,
                    msg.seq,
                    msg.stamp,
                    job.digest,
                    job.status,
                    job.pose_m,
                    pack_frame(job.frame, job.tables),
                    new_trajectory=job.restart,
                    client=self.client,
                    **self.fence(),
                )
            except Exception as exc:  # noqa: BLE001 - e.g. disk full: publish nothing the store lacks
                return exc
            store_ms = (time.perf_counter() - t_store) * 1000.0
            timings.update(store_commit=store_ms, **{f"store_commit.{k}": v for k, v in phases.items()})
        timings["registration"] = job.reg_ms
        timings.update({f"registration.{k}": float(v) for k, v in job.reg_timings.items()})
        timings["core_wait"] = wait_ms + run_delay_ms() - w0  # runnable but without a core, lane and team
        # before the pose goes out: whoever has the pose and waits for the after-pose work waits for this. Caught up,
        # that work lets the pose through the router to its client first
        self._submit_after_pose(job, head_start=self.ctx.config.pose_head_start_ms > 0)
        cov = job.reg.covariance
        self.publish_pose(msg.seq, msg.stamp, job.pose_m, job.status, job.digest, timings, job.restart, cov)
        return None

    def publish_pose(self, seq, stamp, pose_m, status, digest, timings, restart, covariance=None) -> None:
        """Record the pose for queries and publish it (schemas/pose_v1.py: each version on its key); a relocalised
        pose replaces the one of its seq."""
        pose = PoseEstimate(
            stream=self.stream,
            seq=seq,
            stamp=stamp,
            pose=pose_m.tolist(),
            status=status,
            timings_ms=timings,
            sent_at=time.time(),
            covariance=None if covariance is None else np.asarray(covariance, float).tolist(),
        )
        self.trajectory.record(pose, pose_m, digest, restart)
        t_encode = time.perf_counter()
        puts = pose_puts(pose)
        self.ctx.stats.observe("pose_encode", (time.perf_counter() - t_encode) * 1000.0)
        # counted first: a client holding the pose (another thread may wake it before put returns) finds it counted
        self.ctx.stats.inc("relocalised" if status == "relocalised" else "frames_out")
        for key, data in puts:
            self.ctx.put(key, data)

    def _submit_after_pose(self, job: FrameJob, head_start: bool = False) -> None:
        """The frame's work after its pose, handed to the after-pose thread once (the first call of the phases')."""
        if job.after is None:
            wait = self.ctx.config.pose_head_start_ms / 1000.0 if head_start else None
            job.after = self.threads.submit_after(self.ctx.after_pose, self, job, head_start_s=wait)

    def _observe_frame(self, job: FrameJob) -> None:
        stats, timings = self.ctx.stats, job.timings
        stats.observe("registration", job.reg_ms)
        for stage in ("validate", "after_pose_wait", "core_wait", "occupancy_hop"):
            stats.observe(stage, timings[stage])
        if self.ctx.store is not None:
            stats.observe("store_commit", timings["store_commit"])

    # -- helpers of the phases ---------------------------------------------------------------------------------------
    def _queued(self) -> bool:
        return self.ctx.frames_queued(self.stream)

    def frames_waiting(self, entered: int) -> bool:
        """Whether a frame of the stream came after the one that entered the lane as `entered`."""
        return self.entered != entered or self._queued()

    def _report(self, code: str, message: str, seq: int | None) -> None:
        self.ctx.report_error(self.stream, code, message, keys.occupancy(self.stream), seq)

    def _new_trajectory(self) -> None:
        """Seq 0 (or a stream's first frame): the OccVO reset, paging and tiles started again."""
        self.threads.wait_map()
        self.vo = self.vo or self.ctx.occvo(self.ctx.occvo_config, threads=self.ctx.config.kernel_threads)
        self.vo.reset()
        self.pager.reset()
        self.map.reset()
        self.snapshot.restart()

    def store_failed(self, seq: int, exc: Exception, what: str) -> None:
        store_failed(self, seq, exc, what)

    def drop_state(self, fenced: bool) -> None:
        """A write or read failed: the OccVO goes (the stream resumes from the store at its next frame); fenced:
        the lease too (another worker owns the stream now)."""
        self.vo = None
        if fenced:
            self.epoch = None

    def flush_map(self) -> None:
        """The tiles held back for a frame that did not come (refused, or none followed)."""
        if self.map.pending and self.vo is not None and self.trajectory.seqs and self.threads.map is not None:
            cut = self.map.cut(self.vo)
            self.threads.submit_map(self.map.send, self.trajectory.last_seq, False, cut, {}, [])

    # -- open and close ----------------------------------------------------------------------------------------------
    def reopen(self) -> None:
        """Rebuild the OccVO from the stream's snapshot and journal, as it was after the last committed frame."""
        self.ctx.catch_up.begin(self.stream)
        t0 = time.perf_counter()
        self.vo, snap_seq = load_snapshot(self)
        resume(self, snap_seq, t0)

    def close(self) -> None:
        """An idle stream: its threads end; with a store its OccVO is snapshotted and dropped (the next frame reopens
        it from the store), without one it stays in memory (it is the only copy)."""
        self.threads.drain()
        self.flush_map()
        self.threads.close()
        if self.ctx.store is None or self.vo is None:
            return
        self.snapshot.idle.wait()
        if self.snapshot.unsaved and self.may_write:
            self.ctx.snapshots.write_now(self.stream, self.snapshot, self.trajectory.last_seq, self.vo, self.fence())
        self.vo = None  # heap trimmed by the worker
        self.pager.reset()
        self.map.reset()
