"""The registration worker: admits streams, routes each frame to its stream's session (services/registration/
session.py), evicts idle sessions; its Zenoh wiring is the occupancy subscriber, the pose and trajectory queryables
and the shard's liveliness token."""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from occvo_core.errors import ConfigError
from occvo_schemas import keys
from occvo_schemas.models import OccupancyFrameMsg
from occvo_services.os_tuning import trim_heap
from occvo_services.registration.claims import Claims
from occvo_services.registration.frame_job import SessionContext
from occvo_services.registration.membership import Leases, Placement
from occvo_services.registration.paging import MIN_SAFE_RADIUS_M
from occvo_services.registration.placing import Placing
from occvo_services.registration.queries import Queries
from occvo_services.registration.retention import Retention
from occvo_services.registration.scheduling import CatchUp, Scheduler
from occvo_services.registration.session import StreamSession
from occvo_services.registration.snapshots import SnapshotWriter
from occvo_services.registration.store_faults import StoreOutage
from occvo_services.runtime import Worker, WorkerConfig
from occvo_services.store.factory import open_store
from occvo_services.store.url import redact
from occvo_services.telemetry import log_event
from occvo_services.wire import blocking_at
from occvo_services.worker_cli import worker_main

FRAME_MB_PER_VOXEL = 256 / 2**20  # a frame's cost to the resident set while it is registered, about twice measured


class RegistrationWorker(Worker):
    """Occupancy frames -> OccVO poses and map tiles, one session a stream."""

    role = "registration"

    def __init__(self, config: WorkerConfig):
        super().__init__(config)
        from occvo_core import OccVO, OccVOConfig

        self.evict_off = config.working_radius_m is not None and config.store_url is None
        if self.evict_off:  # the deploy config sets a radius; eviction starts when a store is given
            self.config = config = config.model_copy(update={"working_radius_m": None})
        radius = config.working_radius_m
        if radius is not None and radius <= config.tile_m:
            raise ConfigError(
                f"working_radius_m ({radius}) must exceed tile_m ({config.tile_m}): tiles come back "
                "within working_radius_m - tile_m"
            )
        members = config.placement == "members"
        if members and not config.store_url:
            raise ConfigError('placement "members" needs a store: the workers hand streams over through it')
        # under "members" every write is under the stream's lease: none unfenced
        self.store = (
            open_store(config.store_url, config.store_sync.upper(), fenced_only=members) if config.store_url else None
        )
        self.placement = self.leases = self.placing = None
        if members:
            self.placement = Placement(self.worker_id, self.store, config.lease_s, self.log)
            self.leases = Leases(self.store, self.worker_id, config.lease_s, self.placement, self.log, self._serving)
            claims = Claims(config.max_streams_per_client, config.idle_stream_s, self.placement.members)
            self.placing = Placing(self._placed, claims.claim)  # decided off Zenoh's callback: it may ask the store
        self.sessions: dict[str, StreamSession] = {}
        self._sessions_lock = threading.Lock()
        occvo_config = OccVOConfig.load(config.occvo_config) if config.occvo_config else OccVOConfig()
        if config.warm_up:
            self._warm_up(occvo_config)
        self.scheduler = Scheduler(config.after_pose_nice, self.stats, self.log)
        snapshots = None
        if self.store is not None:
            snapshots = SnapshotWriter(
                self.store, self.stats, self.log, self.report_error, self.scheduler.background_thread
            )
        self.outage = StoreOutage(self.store, self.stopping, self.stats, self.log) if self.store is not None else None
        self.ctx = SessionContext(
            config, occvo_config, OccVO, self.store, self.stats, self.log, self.scheduler, snapshots,
            self._put, self.report_error, self._frames_queued, self._busy_lanes, leases=self.leases,
            catch_up=CatchUp(), outage=self.outage,
        )  # fmt: skip
        self.queries = Queries(self)
        self.retention = Retention(self) if self.store is not None else None
        if self.store is not None and self.placement is None:
            for stream in filter(self.owns, self.store.streams()):  # queries answer at once; resumed at the next frame
                self.session_of(stream).load_trajectory()

    def _warm_up(self, occvo_config) -> None:
        """Before the worker is announced: no kernel compiles while frames wait (occvo_core.warm_up), in a thread that
        ends: its OpenMP team goes with it."""
        from occvo_core.warm_up import warm_up

        ready = {}
        warming = threading.Thread(target=lambda: ready.update(warm_up(occvo_config, self.config.kernel_threads)))
        warming.start()
        warming.join()
        log_event(self.log, "kernels ready", **ready)
        trim_heap()

    # -- sessions ------------------------------------------------------------------------------------------------------
    def session_of(self, stream: str) -> StreamSession:
        with self._sessions_lock:
            if stream not in self.sessions:
                self.sessions[stream] = StreamSession(stream, self.ctx)
            return self.sessions[stream]

    def sessions_now(self) -> list[tuple[str, StreamSession]]:
        with self._sessions_lock:
            return list(self.sessions.items())

    def owns(self, stream: str) -> bool:
        """This worker's shard registers the stream (a malformed stream id is shard 0's to report); placement
        "members": it is the stream's owner among the live workers."""
        if self.placement is not None:
            if not keys.STREAM_RE.match(stream):
                return min(self.placement.live) == self.worker_id
            return self.placement.owner(stream) == self.worker_id
        c = self.config
        return keys.shard_of(stream, c.shards) == c.shard if keys.STREAM_RE.match(stream) else c.shard == 0

    def answers(self, stream: str) -> bool:
        """Whether this worker answers queries of a stream it has a session of (placement members: while it owns it)."""
        return self.placement is None or self.owns(stream)

    def _on_occupancy(self, sample: zenoh.Sample) -> None:
        # the session judges the seq against its committed trajectory: a step back may be a resend
        if self.placement is not None:  # the owner decided only for a frame that decoded and its client may send
            self.enqueue(sample, OccupancyFrameMsg, self._route, judge_seq=False, place=self.placing)
        elif self.owns(keys.stream_of(str(sample.key_expr))):  # another shard's stream: not ours to count or judge
            self.enqueue(sample, OccupancyFrameMsg, self._route, judge_seq=False)

    def _placed(self, msg) -> bool:
        """Placement members: whether this worker owns the decoded frame's stream (the store away: not decided, the
        frame answered store_unavailable by one worker; the client sends it again)."""
        self.stats.inc("frames_placed")
        try:
            return self.owns(msg.stream)
        except Exception as exc:  # noqa: BLE001 - a worker never dies of one frame
            if not self.outage.saw(exc):
                raise
            if self.reports_input(msg.stream):
                why = f"seq {msg.seq} not placed: {self.outage.why}; send it again"
                self.report_error(msg.stream, "store_unavailable", why, keys.occupancy(msg.stream), msg.seq)
            return False

    def reports_input(self, stream: str) -> bool:
        """Placement members: every worker decodes every frame; the first live worker reports one that did not."""
        return self.placement is None or min(self.placement.live) == self.worker_id

    def frame_cost_mb(self, msg) -> float:
        """A frame's registration: its preprocessing, covariances, local map window and GICP pairs grow with its
        voxels (FRAME_MB_PER_VOXEL, measured with benchmarks/hostile_clients.py --steps heavy)."""
        return FRAME_MB_PER_VOXEL * msg.occupancy.labels.shape[0]

    def _route(self, stream: str, item) -> None:
        """A frame to its session, unless its client is at its store quota (services/registration/retention.py)."""
        client, seq = self.admission.owner(stream), item[0].seq
        if self.retention is not None and (why := self.retention.refuse(stream, client, seq)) is not None:
            self.stats.inc("frames_refused_quota")
            self.report_error(stream, "store_quota", why, keys.occupancy(stream), seq)
            return
        self.session_of(stream).handle(item, client)

    def forget_idle(self, stream: str, delete):
        """delete() while no lane of the stream is open or opens; its session goes if delete() returns something.
        None: the stream is live (or delete() found nothing to do)."""
        with self._lanes_lock:
            if stream in self.lanes or stream in self._retired:
                return None
            done = delete()
            if done is not None:
                with self._sessions_lock:
                    self.sessions.pop(stream, None)
            return done

    def retire_stream(self, stream: str) -> None:
        session = self.sessions.get(stream)
        if session is None:
            return
        session.close()

    def not_held(self, stream: str, seq: int) -> None:
        """A frame not held while the store is away: the stream's later frames wait for it (as for a refused write)."""
        with self._sessions_lock:
            session = self.sessions.get(stream)
        if session is not None:
            session.refused(seq)

    def _serving(self) -> set[str]:
        """The streams this worker has a lane or a lease-holding session of (their lease rows are kept)."""
        with self._lanes_lock:
            streams = set(self.lanes) | set(self._retired)
        return streams | {stream for stream, s in self.sessions_now() if s.epoch is not None}

    def store_away(self) -> str | None:
        """Why the store cannot be reached now (frames that cannot be held are answered store_unavailable), or None."""
        return self.outage.why if self.outage is not None and self.outage.down else None

    def _frames_queued(self, stream: str) -> bool:
        lane = self.lanes.get(stream)
        return lane is not None and lane.queue.q.qsize() > 0

    def _busy_lanes(self) -> int:
        return sum(1 for lane in list(self.lanes.values()) if lane.busy)

    def _put(self, key: str, data: bytes) -> None:
        self.session.put(key, data, **blocking_at(key))

    # -- lifecycle -----------------------------------------------------------------------------------------------------
    def declare(self) -> None:
        s = self.session
        self._declared += [
            s.declare_subscriber(keys.occupancy("*"), self._on_occupancy),
            s.declare_queryable(keys.pose_latest("*"), self.bounded(self.queries.on_pose_latest)),
            s.declare_queryable(keys.trajectory("*"), self.bounded(self.queries.on_trajectory)),
        ]
        # clients watch their shard's token: frames sent while their stream's worker is away are resent when it is back
        if self.placement is not None:
            token = keys.registration_shard(0, 0, self.worker_id)
            self._declared.append(self.placement.declare(s))
            self.leases.start()
        else:
            token = keys.registration_shard(self.config.shard, self.config.shards, self.worker_id)
        self._declared.append(s.liveliness().declare_token(token))
        c = self.config
        if self.evict_off:
            log_event(self.log, "working_radius_m ignored: eviction needs store_path (the evicted map goes there)")
        if self.store is not None:
            self.retention.start()
            log_event(
                self.log,
                "trajectory store",
                store=redact(c.store_url),
                streams=sorted(self.sessions),
                working_radius_m=c.working_radius_m,
                snapshot_every=c.snapshot_every,
                max_store_mb_per_client=c.max_store_mb_per_client,
                max_stored_streams_per_client=c.max_stored_streams_per_client,
                stream_ttl_s=c.stream_ttl_s,
            )
            if c.working_radius_m is not None and c.working_radius_m < MIN_SAFE_RADIUS_M:
                log_event(
                    self.log,
                    "working radius below a frame's reach: eviction changes registration",
                    working_radius_m=c.working_radius_m,
                )

    def drain(self) -> None:
        """Wait for every session's work after its last pose (its map update, loop closure, snapshot queueing)."""
        for _, s in self.sessions_now():
            s.threads.drain()

    def snapshots_written(self, timeout: float | None = None) -> bool:
        """Wait until no snapshot is queued or being written (tests and benchmarks)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        self.drain()
        for _, s in self.sessions_now():
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not s.snapshot.idle.wait(left):
                return False
        return True

    def after_leaving(self) -> None:
        """Off the network (the frames in hand finished): end the sessions' threads, then snapshot every session
        with unsnapshotted frames."""
        self.scheduler.shutdown()
        in_hand = {stream for stream, lane in list(self.lanes.items()) if not lane.strand.idle}
        for stream, s in self.sessions_now():
            if stream not in in_hand:  # drained already: its strands end now
                s.threads.close()
        if self.store is None:
            self.scheduler.close_pools()
            return
        self.retention.stop()
        t0 = time.perf_counter()
        self.ctx.snapshots.close()
        self._shutdown_step("queued snapshots written", t0)
        for stream, s in self.sessions_now():
            if stream in in_hand:  # a frame in hand that did not finish in time: its OccVO is not touched from here
                continue
            t0 = time.perf_counter()
            voxels = s.save()  # in place, if it has frames no snapshot has
            if voxels is not None:
                self._shutdown_step("snapshot at shutdown", t0, stream=stream, map_voxels=voxels)
        if self.leases is not None:  # the next owners take the streams at once
            self.placing.close()
            self.leases.stop()
            for stream, s in self.sessions_now():
                if s.epoch is not None and stream not in in_hand:
                    self.leases.release(stream)
        self.scheduler.close_pools()
        t0, sizes = time.perf_counter(), self.store.file_sizes_mb()  # the WAL is checkpointed into the file on close
        self.store.close()
        self._shutdown_step("store closed", t0, **sizes)

    def _shutdown_step(self, step: str, t0: float, **fields) -> None:
        """Log a shutdown step's time; a slow one at WARNING, since a supervisor's stop timeout may cut it short."""
        took = time.perf_counter() - t0
        log_event(self.log, step, logging.WARNING if took > 5.0 else logging.INFO, seconds=round(took, 2), **fields)


def _args(p) -> None:
    p.add_argument("--shard", type=int, help="register the streams of this shard (0..shards-1)")
    p.add_argument("--shards", type=int, help="registration workers sharing the streams (by a hash of the stream id)")
    p.add_argument("--tile-m", type=float)
    p.add_argument(
        "--map-coalesce-s", type=float, help="with frames waiting, one map update for them at most this often (0: each)"
    )
    p.add_argument(
        "--pose-head-start-ms", type=float, help="caught up, a pose's lead over the frame's work after it (0: none)"
    )
    p.add_argument("--occvo-config")
    p.add_argument("--store-path", help="SQLite file of the trajectories, snapshots and evicted map (default: none)")
    p.add_argument("--snapshot-every", type=int, help="frames between state snapshots")
    p.add_argument("--snapshot-max-share", type=float, help="snapshots take at most this share of a stream's time")
    p.add_argument("--working-radius-m", type=float, help="evict map tiles farther than this from the ego to the store")
    p.add_argument(
        "--after-pose-nice", type=int, help="niceness of the work after a pose, relative to the lanes (0: same)"
    )
    p.add_argument("--store-sync", choices=["full", "normal"], help="full: a published pose survives a power cut too")
    p.add_argument(
        "--placement",
        choices=["shards", "members"],
        help="members: the live registration workers share the streams, each under a lease in the shared store",
    )
    p.add_argument("--lease-s", type=float, help="placement members: how long a silent owner keeps its streams")
    p.add_argument("--max-store-mb-per-client", type=int, help="store bytes one client may keep (MB)")
    p.add_argument("--max-stored-streams-per-client", type=int, help="stored streams one client may keep")
    p.add_argument("--stream-ttl-s", type=float, help="a stored stream idle this long is deleted (default: kept)")


def main(argv: list[str] | None = None) -> int:
    return worker_main(RegistrationWorker, argv, extra_args=_args, prog="python -m occvo_services.registration_worker")
