"""The pose path, a session's first part (PosePath): a frame's phases up to its published pose,

    validate -> sequence -> register -> commit -> publish

then the frame goes on as a RegisteredFrame to the work after its pose (after_pose.AfterPose, which this part
builds). It owns the stream's committed trajectory (queries read the view it publishes), the jump held, the frames
refused, the count of frames entered, the lease's epoch and the client."""

from __future__ import annotations

import time

import numpy as np

from occvo_core.errors import InvalidFrameError
from occvo_schemas import keys
from occvo_schemas.models import PoseEstimate
from occvo_schemas.pose_v1 import pose_puts
from occvo_services.os_tuning import run_delay_ms
from occvo_services.registration.after_pose import AfterPose
from occvo_services.registration.frame_job import STATUS, FrameJob, SessionContext, frame_job
from occvo_services.registration.scheduling import StreamThreads
from occvo_services.registration.sequencing import Sequencing
from occvo_services.registration.store_faults import Refusals, store_back, store_failed
from occvo_services.registration.trajectory import StreamTrajectory, pose_message
from occvo_services.store.blobs import legacy_frame_digest, pack_frame
from occvo_services.store.errors import FencedError, StoreUnavailable
from occvo_services.store.records import StoredPose
from occvo_services.telemetry import log_event


class PosePath:
    """A stream's frames up to their poses; nothing outside writes these fields."""

    def __init__(self, stream: str, ctx: SessionContext, threads: StreamThreads):
        self.stream, self.ctx, self.threads = stream, ctx, threads
        self.trajectory = StreamTrajectory()
        self.after = AfterPose(stream, ctx, threads, self)
        self.sequencing = Sequencing(ctx.config, ctx.stats, self.report)
        self.refusals = Refusals(self.report)  # frames refused or turned away: the ones after the first wait
        self.entered = 0  # frames that entered the lane: the work after a pose sees whether another came
        self.epoch: int | None = None  # placement "members": the fencing epoch of this worker's lease on the stream
        self.client: str | None = None  # whose frames these are (the worker's admission): the store records it

    def load_trajectory(self) -> None:
        """The stored trajectory, for queries and resends (the OccVO is resumed at the stream's next frame); the one
        in memory stays if the store cannot be read."""
        t = StreamTrajectory()
        for p in self.ctx.store.poses(self.stream):
            t.append(p.seq, p.stamp, p.pose, p.status, p.digest)
        if len(t):
            t.publish(pose_message(self.stream, t.stored(t.last_seq)))
        self.trajectory = t

    # -- a frame, phase by phase ------------------------------------------------------------------------------------
    def handle(self, item, client: str | None) -> None:
        """The lane's handler: one frame. Counted as entered, so the last frame's work after its pose sees that
        another came (its map update can wait for this one's)."""
        self.entered += 1
        self.client = client
        self.threads.head_start.set()  # the last pose's work after it starts now if it still waits
        tail = self.threads.tail
        try:
            self._frame(item, self.entered)
        finally:
            self.ctx.catch_up.end(self.stream)  # reopened: caught up with its first frame after it
            if self.threads.tail is tail and self.threads.after is not None and not self._queued():
                # no work after a pose followed (refused, a resend) and no frame waits: the tiles held back go now
                self.threads.submit_after(self.after.flush_map)

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
            if not self._own(job) or self._answer_resend(job) or self.refusals.waits(job.msg.seq):
                return
            held = self.sequencing.confirmed(job, self.trajectory)
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
            self.refusals.refused(first)

    def _validate(self, msg, entered: int) -> FrameJob | None:
        """The frame built and checked before any reset (a bad first frame leaves the old trajectory intact)."""
        try:
            return frame_job(msg, self.stream, entered)
        except InvalidFrameError as exc:
            self.report("invalid_frame", f"seq {msg.seq}: {exc.reason}", msg.seq)
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
        self.after.drop()
        self.load_trajectory()  # before the epoch: a read that failed takes the lease again at the next frame
        self.epoch = epoch
        return True

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

    def _sequence(self, job: FrameJob, confirmed: bool = False) -> bool:
        """The frame's place after the committed trajectory (sequencing.Sequencing); then the OccVO it registers
        on: a new one at seq 0, else the stream's, resumed from the store if this process has none."""
        if not self.sequencing.place(job, self.trajectory, confirmed):
            return False
        if job.restart:
            self.after.restart()
        elif self.after.vo is None:
            self.after.reopen()
        if self.ctx.config.kernel_threads == 0:
            self.after.share_cores(self.ctx.scheduler.fair_threads(self.ctx.busy_lanes()))
        return True

    def _register_commit_publish(self, job: FrameJob, waited0: float) -> bool:
        """Register, commit, publish. Caught up, the three are one call in the kernel team's thread (a lane woken
        between them waited behind the team's spinning OpenMP threads) and the work after the pose waits until it
        is out; with frames waiting, that work starts as soon as the frame is registered. True: the pose is out."""
        self.ctx.catch_up.wait_turn(self.stream)
        job.t_reg = time.perf_counter()
        backlog = self._queued()
        self.threads.start()
        team, vo = self.ctx.scheduler, self.after.vo
        try:
            try:
                if backlog:
                    _, team_wait = team.kernels(vo, self._register, job)
                    self._submit_after_pose(job)
                    failed = self._commit_and_publish(job, run_delay_ms() - waited0 + team_wait)
                else:
                    failed, _ = team.kernels(vo, self._caught_up, job, run_delay_ms() - waited0)
            except InvalidFrameError as exc:  # from register: nothing registered, nothing to do after it
                if job.restart and self.ctx.store is not None:
                    self.after.drop()  # reset for nothing: the stored trajectory stands and resumes at the next frame
                self.report("invalid_frame", f"seq {job.msg.seq}: {exc.reason}", job.msg.seq)
                return False
            if failed is not None:
                job.pose_out.set_result(False)
                self._submit_after_pose(job)
                job.after.result()  # its OccVO.complete: then the state goes, rebuilt from the store
                store_failed(self, job.msg.seq, failed, "not stored, pose not published")
                if not isinstance(failed, FencedError):
                    self.refusals.refused(job.msg.seq)
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
        self.ctx.scheduler.kernels_done(self.after.vo.threads)
        return self._commit_and_publish(job, lane_wait + run_delay_ms() - w_call)

    def _register(self, job: FrameJob) -> None:
        """Preprocess and registration through fine GICP (OccVO.register): the pose, nothing changed yet."""
        reg = self.after.vo.register(job.frame)
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
        """The frame's work after its pose, handed to the after-pose strand once (the first call of the phases')."""
        if job.after is None:
            wait = self.ctx.config.pose_head_start_ms / 1000.0 if head_start else None
            job.after = self.threads.submit_after(self.ctx.after_pose, self.after, job.registered(), head_start_s=wait)

    def _observe_frame(self, job: FrameJob) -> None:
        stats, timings = self.ctx.stats, job.timings
        stats.observe("registration", job.reg_ms)
        for stage in ("validate", "after_pose_wait", "core_wait", "occupancy_hop"):
            stats.observe(stage, timings[stage])
        if self.ctx.store is not None:
            stats.observe("store_commit", timings["store_commit"])

    # -- what the work after a pose asks of the pose path (after_pose.PoseSide) -----------------------------------
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

    def stored(self, seq: int) -> StoredPose | None:
        return self.trajectory.stored(seq)

    def last_seq(self) -> int | None:
        return self.trajectory.last_seq if len(self.trajectory) else None

    def frames_waiting(self, entered: int) -> bool:
        """Whether a frame of the stream came after the one that entered the lane as `entered`."""
        return self.entered != entered or self._queued()

    def store_failed(self, seq: int, exc: Exception, what: str) -> None:
        store_failed(self, seq, exc, what)

    def drop_state(self, fenced: bool) -> None:
        """A write or read failed: the OccVO goes (the stream resumes from the store at its next frame); fenced:
        the lease too (another worker owns the stream now)."""
        self.after.drop()
        if fenced:
            self.epoch = None

    # -- helpers -----------------------------------------------------------------------------------------------------
    def _queued(self) -> bool:
        return self.ctx.frames_queued(self.stream)

    def report(self, code: str, message: str, seq: int | None) -> None:
        self.ctx.report_error(self.stream, code, message, keys.occupancy(self.stream), seq)
