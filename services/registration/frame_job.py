"""What the registration worker lends a session (SessionContext) and what one frame hands from phase to phase
(FrameJob)."""

from __future__ import annotations

import logging
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.registration.after_pose import after_pose

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

    config: object
    occvo_config: object
    occvo: type
    store: object
    stats: object
    log: logging.Logger
    scheduler: object
    snapshots: object
    put: object
    report_error: object
    frames_queued: object  # stream -> whether frames of it wait in its lane
    busy_lanes: object  # () -> lanes registering now
    after_pose: object = after_pose  # (session, job): the work after a pose (services/registration/after_pose.py)
    leases: object = None  # placement "members": the worker's stream leases (membership.Leases)
    catch_up: object = None  # scheduling.CatchUp: reopened sessions register first
    outage: object = None  # with a store: store_faults.StoreOutage, the store away until a probe reaches it


@dataclass
class FrameJob:
    """One frame's way through the phases: what each phase hands the next."""

    msg: object
    frame: OccupancyFrame
    tables: tuple
    digest: bytes
    timings: dict
    t_valid: float
    entered: int
    restart: bool = False
    t_reg: float = 0.0
    reg: object = None  # OccVO.register's result, once registered
    pose_m: np.ndarray | None = None
    status: str = "ok"
    reg_ms: float = 0.0
    reg_timings: dict = field(default_factory=dict)
    pose_out: Future = field(default_factory=Future)  # True once the pose is committed and published
    after: Future | None = None  # its work after the pose, once handed to the after-pose thread
