"""The registration worker's Zenoh wiring: a session, the occupancy subscriber, the pose and trajectory queryables,
the shard's liveliness token; each job is a module of services/registration/."""

from __future__ import annotations

import queue
import threading
from concurrent.futures import ThreadPoolExecutor

from occvo_core.errors import ConfigError
from occvo_core.registration.kernels import own_team
from occvo_schemas import keys
from occvo_services.os_tuning import IdleTeam, name_os_thread, trim_heap
from occvo_services.registration.after_pose import AfterPose
from occvo_services.registration.durability import Durability
from occvo_services.registration.lane import StreamLanes
from occvo_services.registration.map_publisher import MapPublisher
from occvo_services.registration.paging import MIN_SAFE_RADIUS_M, Paging
from occvo_services.registration.queries import Queries
from occvo_services.registration.state import StreamState
from occvo_services.runtime import Worker, WorkerConfig, worker_main
from occvo_services.store import TrajectoryStore
from occvo_services.telemetry import log_event

SNAPSHOT_BYTES_PER_S = 200e6  # a snapshot's writing speed until this worker has measured one (SSD: 150-270 MB/s)


class RegistrationWorker(StreamLanes, AfterPose, Durability, Paging, MapPublisher, Queries, Worker):
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
        self.store = TrajectoryStore.open(config.store_url, config.store_sync.upper()) if config.store_url else None
        self._snapshots: queue.Queue = queue.Queue()
        self._boost_refused = False
        self._snapshot_writer = None
        self._snapshot_s_per_byte = 1 / SNAPSHOT_BYTES_PER_S  # measured by each snapshot written
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

            # in a thread that ends: its OpenMP team goes with it (AfterPose._background_thread)
            ready = {}
            warming = threading.Thread(target=lambda: ready.update(warm_up(self.occvo_config, config.kernel_threads)))
            warming.start()
            warming.join()
            log_event(self.log, "kernels ready", **ready)
            trim_heap()
        # the one thread whose kernels run on several cores (occvo_core.registration.kernels.use_threads): a lane
        # hands its frame's kernel work to it when it may use more than one core
        self._team = ThreadPoolExecutor(1, "kernels", initializer=name_os_thread)
        self._idle_team = IdleTeam()
        if not self._team.submit(own_team).result():
            log_event(self.log, "another thread of this process runs kernels on several cores: lanes run on one")

    def owns(self, stream: str) -> bool:
        """This worker's shard registers the stream (a malformed stream id is shard 0's to report)."""
        c = self.config
        return keys.shard_of(stream, c.shards) == c.shard if keys.STREAM_RE.match(stream) else c.shard == 0

    def declare(self) -> None:
        s = self.session
        self._declared += [
            s.declare_subscriber(keys.occupancy("*"), self._on_occupancy),
            s.declare_queryable(keys.pose_latest("*"), self.bounded(self._on_pose_latest)),
            s.declare_queryable(keys.trajectory("*"), self.bounded(self._on_trajectory)),
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


def main(argv: list[str] | None = None) -> int:
    return worker_main(RegistrationWorker, argv, extra_args=_args, prog="python -m occvo_services.registration_worker")
