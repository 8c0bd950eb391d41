"""What the registration worker lends a session (SessionContext), what one frame hands from phase to phase on the
pose path (FrameJob, built and validated by frame_job) and what the pose path hands the work after the pose
(RegisteredFrame: the edge between a session's two parts)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID
from occvo_services.registration.after_pose import AfterPose
from occvo_services.store.blobs import frame_digest

if TYPE_CHECKING:
    from occvo_core import OccVOConfig
    from occvo_core.odometry import Registration
    from occvo_schemas.models import OccupancyFrameMsg
    from occvo_services.registration.membership import Leases
    from occvo_services.registration.scheduling import CatchUp, Scheduler
    from occvo_services.registration.snapshots import SnapshotWriter
    from occvo_services.registration.store_faults import StoreOutage
    from occvo_services.store.protocols import FrameLog
    from occvo_services.telemetry import Stats
    from occvo_services.worker_config import WorkerConfig

STATUS = {  # OccVO statuses as a published pose names them
    "ok": "ok",
    "lost": "lost",
    "initialised": "initialised",  # version 1 of the wire calls it reinitialised (schemas/pose_v1.py)
    "reinitialised": "reinitialised",
    "degenerate": "degenerate",
}


@dataclass
class SessionContext:
    """What the worker lends its sessions: configuration, the store, the kernel team, the snapshot writer and the
    outputs (put: a Zenoh put of the worker's session; report_error: an error event)."""

    config: WorkerConfig
    occvo_config: OccVOConfig
    occvo: type  # OccVO
    store: FrameLog | None  # open_store's: it answers every protocol of store.protocols.TRAJECTORY_STORE
    stats: Stats
    log: logging.Logger
    scheduler: Scheduler
    snapshots: SnapshotWriter | None  # with a store
    put: Callable[[str, bytes], None]  # a Zenoh put of the worker's session
    report_error: Callable[..., object]  # Worker.report_error: an error event
    frames_queued: Callable[[str], bool]  # stream -> whether frames of it wait in its lane
    busy_lanes: Callable[[], int]  # lanes registering now
    after_pose: Callable = AfterPose.run  # (its AfterPose, RegisteredFrame): the work after a pose
    leases: Leases | None = None  # placement "members": the worker's stream leases
    catch_up: CatchUp | None = None  # reopened sessions register first
    outage: StoreOutage | None = None  # with a store: the store away until a probe reaches it


@dataclass
class FrameJob:
    """One frame's way through the phases: what each phase hands the next."""

    msg: OccupancyFrameMsg
    frame: OccupancyFrame
    tables: tuple
    digest: bytes
    timings: dict
    t_valid: float
    entered: int
    restart: bool = False
    t_reg: float = 0.0
    reg: Registration | None = None  # OccVO.register's result, once registered
    pose_m: np.ndarray | None = None
    status: str = "ok"
    reg_ms: float = 0.0
    reg_timings: dict = field(default_factory=dict)
    pose_out: Future = field(default_factory=Future)  # True once the pose is committed and published
    after: Future | None = None  # its work after the pose, once handed to the after-pose thread

    def registered(self) -> RegisteredFrame:
        return RegisteredFrame(
            self.msg, self.frame, self.digest, self.restart, self.entered, self.reg, self.pose_m, self.reg_timings,
            self.t_valid, self.pose_out,
        )  # fmt: skip


@dataclass(frozen=True)
class RegisteredFrame:
    """A frame the pose path registered, as the work after its pose gets it: pose_out is True once its pose was
    committed and published (False: nothing of it is stored or published)."""

    msg: OccupancyFrameMsg
    frame: OccupancyFrame
    digest: bytes
    restart: bool  # a new trajectory's first frame
    entered: int  # its count among the frames that entered the lane (whether another came since)
    reg: Registration
    pose_m: np.ndarray
    reg_timings: dict  # OccVO.register's stages (complete's are the others)
    t_valid: float  # when the pose path had it validated (the stages' total)
    pose_out: Future


def frame_job(msg: OccupancyFrameMsg, stream: str, entered: int) -> FrameJob:
    """A frame's job: the frame built and validated (InvalidFrameError), digested in the compact form it came in."""
    frame = OccupancyFrame(
        msg.occupancy.to_points(),
        msg.occupancy.labels.to_numpy().copy(),
        index=msg.seq,
        stamp=msg.stamp,
        meta={"stream": stream, "source": msg.source},
    )
    frame.validate()
    tables = msg.occupancy.index_tables(OCC3D_GRID)
    digest = frame_digest(frame.points, frame.labels, msg.stamp, tables)
    return FrameJob(msg, frame, tables, digest, dict(msg.timings_ms), 0.0, entered)
