"""One stream's session in the registration worker, as two parts with one typed edge between them (docs/service.md
has the picture):

    pose path (pose_path.py):  validate -> sequence -> register -> commit -> publish
            | RegisteredFrame
    after pose (after_pose.py): complete -> store -> map -> snapshot   (and what a reopen replays, resume.py)

The pose is published only after its commit; the work after it runs in the session's after-pose strand. Each part
owns its fields; the worker and its queries go through the session's methods and read the trajectory view the pose
path publishes."""

from __future__ import annotations

from occvo_services.registration.frame_job import SessionContext
from occvo_services.registration.pose_path import PosePath
from occvo_services.registration.scheduling import StreamThreads
from occvo_services.registration.trajectory import TrajectoryView


class StreamSession:
    """A stream's two parts and their strands; closed (state to the store) and reopened from the store."""

    def __init__(self, stream: str, ctx: SessionContext):
        self.stream, self.ctx = stream, ctx
        self.threads = StreamThreads(stream, ctx.scheduler)
        self.pose = PosePath(stream, ctx, self.threads)
        self.after = self.pose.after

    def handle(self, item, client: str | None = None) -> None:
        """The lane's handler: one frame of `client`'s (the worker's admission: the store records it)."""
        self.pose.handle(item, client)

    def load_trajectory(self) -> None:
        self.pose.load_trajectory()

    def refused(self, seq: int) -> None:
        """A frame not held while the store is away: the stream's later frames wait for it (as for a refused write);
        a resend of a registered frame is answered anyway."""
        view = self.view
        if view is None or seq > view.last_seq:
            self.pose.refusals.refused(seq)

    # -- what others read ----------------------------------------------------------------------------------------------
    @property
    def view(self) -> TrajectoryView | None:
        """The trajectory as last published (queries, quotas): None until the stream has a pose."""
        return self.pose.trajectory.view

    @property
    def vo(self):
        return self.after.vo

    @property
    def map(self):
        return self.after.map

    @property
    def snapshot(self):
        return self.after.snapshot

    @property
    def entered(self) -> int:
        return self.pose.entered

    @property
    def epoch(self) -> int | None:
        return self.pose.epoch

    @property
    def may_write(self) -> bool:
        return self.pose.may_write

    # -- open and close ------------------------------------------------------------------------------------------------
    def close(self) -> None:
        """An idle stream: its strands end; with a store its OccVO is snapshotted and dropped (the next frame reopens
        it from the store), without one it stays in memory (it is the only copy)."""
        self.threads.drain()
        self.after.flush_map()
        self.threads.close()
        self.after.close()

    def save(self) -> int | None:
        """At shutdown: a snapshot of the state in place if it has unsnapshotted frames; the map's voxels, or None."""
        return self.after.save()
