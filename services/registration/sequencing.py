"""The pose path's sequence phase: a frame's place after the stream's committed trajectory (services/flow.judge_seq),
and the jump held until the frame after it confirms it."""

from __future__ import annotations

from typing import TYPE_CHECKING

from occvo_services.flow import judge_seq

if TYPE_CHECKING:
    from occvo_services.registration.frame_job import FrameJob
    from occvo_services.registration.trajectory import StreamTrajectory


class Sequencing:
    """A jump (a seq more than one ahead, within max_seq_jump) is held, not adopted, until the frame after it confirms
    it: one stray seq must not make the stream's real next frames steps back (lossless policy; under "latest" frames
    are dropped on purpose and a jump is taken at once)."""

    def __init__(self, config, stats, report):
        self.config, self.stats, self.report = config, stats, report
        self.held: FrameJob | None = None  # a jump waiting for the frame after it

    def confirmed(self, job: FrameJob, t: StreamTrajectory) -> FrameJob | None:
        """The held jump this frame confirms (it is the held frame's next seq), else None."""
        held = self.held
        if held is None or job.msg.seq != held.msg.seq + 1 or not t.started or held.msg.seq <= t.last_seq + 1:
            return None
        self.held = None
        return held

    def place(self, job: FrameJob, t: StreamTrajectory, confirmed: bool = False) -> bool:
        """Whether the frame registers now: a new trajectory's first (job.restart: seq 0, or no trajectory yet) or
        the next after the committed trajectory; a held jump, a step back or a jump too far does not."""
        seq = job.msg.seq
        job.restart = seq == 0 or not t.started
        if job.restart:
            self.held = None
            return True
        jump = seq - t.last_seq
        # under the "latest" policy frames are dropped on purpose: a gap there is the normal case, not held
        hold = not confirmed and self.config.policy == "lossless"
        if hold and 1 < jump <= self.config.max_seq_jump:
            self.held = job  # a later jump replaces it; the stream's real next frame drops it
            self.stats.inc("seq_held")
            self.report("seq_held", f"seq {seq} is {jump} after seq {t.last_seq}: held until seq {seq + 1}", seq)
            return False
        if jump == 1:
            self.held = None
        known = t.stored(seq) is not None
        older = " and differs from the registered frame" if known else " and is older than the trajectory"
        ok, code, message = judge_seq(seq, t.last_seq, self.config.max_seq_jump, older)
        if code is not None:
            self.stats.inc(code)
            self.report(code, message, seq)
        return ok
