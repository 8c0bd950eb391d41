"""The one config of every worker role (deploy/*.json5 and the command line)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from occvo_core.errors import ConfigError
from occvo_schemas.codec import DEFAULT_MAX_BYTES

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
MIN_SERVED_RSS_MB = 512  # a served worker's smallest memory cap (WorkerConfig.check_served)
Policy = Literal["lossless", "latest"]
# placement "members": snapshots often enough that a moved stream's resume replays a short journal
MEMBERS_SNAPSHOT_EVERY, MEMBERS_SNAPSHOT_SHARE = 5, 0.2


class WorkerConfig(BaseModel):
    """One config for every worker; fields a role does not use are ignored by it (deploy/*.json5)."""

    model_config = ConfigDict(extra="forbid")
    connect: str = DEFAULT_ENDPOINT
    worker_id: str | None = None
    policy: Policy = "lossless"
    queue_size: int = Field(4, ge=1, le=1024)
    max_message_bytes: int = Field(DEFAULT_MAX_BYTES, ge=1024)
    log_level: str = "INFO"
    # a router not up yet is waited for this long at start (one started beside the worker, by systemd or a script,
    # may come up after it); a router that answers and refuses the worker is not. 0: exit at once
    router_wait_s: float = Field(60.0, ge=0)
    # what one client may cost (services/limits.py); the defaults fit a 2-core machine
    max_streams: int = Field(64, ge=1)  # streams a worker serves at once; more get a stream_limit error event
    max_streams_per_client: int = Field(16, ge=1)  # of them, per client (client_identity)
    # who a client is (services/limits.py): "session": the publishing Zenoh session (self-declared without the ACL);
    # "user": the stream id's prefix before its first '.', which the shipped ACL ties to the authenticated user
    client_identity: Literal["session", "user"] = "session"
    idle_stream_s: float = Field(30.0, gt=0)  # a stream without frames this long gives back its lane (and its memory)
    # resident set this worker keeps under (services/memory.py): near it idle streams are evicted and new streams
    # refused (stream_limit). None: no cap. 4 GiB leaves a 24 GiB machine room for the router, the other workers
    # and a model source; the registration worker's admitted streams stay well under it (docs/results.md, Hostile clients)
    max_rss_mb: int | None = Field(4096, ge=64)  # `occvo serve` and `occvo up` ask for MIN_SERVED_RSS_MB at least
    max_seq_jump: int = Field(100_000, ge=1)  # a seq this far beyond the next expected is reported, not adopted
    error_events_per_s: float = Field(20.0, gt=0)  # error events a stream may cause a second (bursts of error_burst)
    error_burst: int = Field(100, ge=1)
    max_query_tiles: int = Field(64, ge=1)  # map: tiles in one reply to a region or wildcard query (a page)
    max_query_streams: int = Field(16, ge=1)  # registration: trajectories in one reply to a wildcard query
    # queries a client may have in work at once (services/query_gate.py); queries with a wildcard stream chunk, all
    # clients together
    max_queries_per_client: int = Field(2, ge=1)
    max_wildcard_queries: int = Field(1, ge=1)
    # inference worker
    source: Literal["replay", "model"] = "replay"
    device: Literal["auto", "cpu", "cuda"] = "auto"
    model_weights: str | None = None  # TinyOccNet state_dict (occvo_services.occupancy_model)
    checkpoint: str | None = None  # TPV-Former checkpoint of the model source (occvo train-occ)
    torch_threads: int = Field(1, ge=1, le=256)
    # model source: voxels the network is less sure of than this are reported free (OccupancyPredictor)
    min_confidence: float = Field(0.0, ge=0, le=1)
    min_ground_confidence: float = Field(0.0, ge=0, le=1)
    camera_mask: bool = False  # model source: keep only the voxels the cameras' rays reach (Occ3D's mask_camera)
    # registration worker
    # shards: registration workers sharing the streams; this one registers the streams of `shard`
    # (occvo_schemas.keys.shard_of: CRC-32 of the stream id mod shards). `occvo up` sets both from a role's count
    shard: int = Field(0, ge=0)
    shards: int = Field(1, ge=1, le=1024)
    # registration: "members": the live registration workers share the streams by rendezvous hashing (keys.owner_of),
    # each stream written by its owner only, under a lease with a fencing epoch in the store (hosts sharing a
    # PostgreSQL store); a lost worker's streams move to the others. lease_s: how long a silent owner keeps them
    placement: Literal["shards", "members"] = "shards"
    lease_s: float = Field(10.0, gt=0)
    # 5..1000 m: a frame's reach (80 m) then spans at most 16 x 16 tiles; 1 m tiles made a map update of over 65,536
    # entries (refused by the map service's decoder) and 0.001 m none at all
    tile_m: float = Field(20.0, ge=5.0, le=1000.0)
    # registration: with frames of a stream waiting, their map tiles go out together, in one update at most this long
    # after the last (every update re-sends whole tiles); a stream caught up gets one a frame. 0: one a frame always
    map_coalesce_s: float = Field(0.5, ge=0)
    # registration: a stream caught up lets its pose reach the client for this long (or until its next frame comes)
    # before the frame's work after the pose (map update, loop closure) takes the cores. 0: no head start
    pose_head_start_ms: float = Field(5.0, ge=0, le=60_000)
    occvo_config: str | None = None
    # registration: cores each stream's kernels may use; 0 = this shard's share of the cores (cores / shards), shared
    # by its streams registering at that moment (one stream alone uses them all). Poses are the same for any value
    kernel_threads: int = Field(0, ge=0, le=256)
    # registration: niceness added to the threads doing the work after a pose (loop closure, map update, eviction,
    # restores) and writing snapshots, so that the cores go to other streams' poses first. 0: the lanes' priority
    after_pose_nice: int = Field(10, ge=0, le=19)
    # registration: a frame's work after its pose taking longer than this is logged with its steps (its stream's next
    # frame waits for it)
    slow_after_pose_s: float = Field(0.5, gt=0)
    # registration: call every kernel once at start-up, before taking frames (compiled on a fresh install, else
    # loaded from numba's cache; see occvo_core/warm_up.py)
    warm_up: bool = True
    # durable state: a SQLite file (a path or sqlite:///path; the registration worker and the map service of one
    # host may share one) or a PostgreSQL database (postgresql://user@host/db) that workers on many hosts share
    store_url: str | None = None
    store_path: str | None = None  # the earlier name of store_url: either may be given, both read the same
    snapshot_every: int = Field(
        20, ge=1
    )  # registration: frames between state snapshots at least (a journal covers the rest)
    # registration: snapshots of a stream take at most this share of its time; a big map is snapshotted less often
    # (a resume replays more journal) instead of stalling every stream (a big map's state takes long to write);
    # None: every snapshot_every frames whatever they cost
    snapshot_max_share: float | None = Field(0.02, gt=0, le=1)
    working_radius_m: float | None = Field(None, gt=0)  # registration: map farther from the ego goes to the store
    # registration with a store (services/registration/retention.py): what one client (client_identity) may keep in
    # it; over either, its frames that would grow the store are refused (store_quota). None: no limit
    max_store_mb_per_client: int | None = Field(1024, ge=1)
    max_stored_streams_per_client: int | None = Field(1000, ge=1)
    # registration: a stored stream without a frame this long is deleted (trajectory, journal, snapshot, cold tiles
    # and, in the same store, its map); None: kept until `occvo store delete` (docs/service.md says why by default)
    stream_ttl_s: float | None = Field(None, gt=0)
    store_sync: Literal["full", "normal"] = (
        "full"  # registration: SQLite synchronous; normal survives kill -9, not power loss
    )

    @model_validator(mode="after")
    def _one_store(self) -> WorkerConfig:
        if self.store_url and self.store_path and self.store_url != self.store_path:
            raise ValueError(f"store_url {self.store_url!r} and store_path {self.store_path!r} name two stores")
        # assigned through __dict__: validate_assignment is off, and a model_copy must not re-run this
        self.__dict__["store_url"] = self.__dict__["store_path"] = self.store_url or self.store_path
        return self

    @model_validator(mode="after")
    def _members_snapshot_often(self) -> WorkerConfig:
        """Placement "members": a moved stream's next owner replays its journal since the last snapshot, so unless
        set, snapshots come every MEMBERS_SNAPSHOT_EVERY frames within MEMBERS_SNAPSHOT_SHARE of a stream's time."""
        if self.placement == "members":
            if "snapshot_every" not in self.model_fields_set:
                self.__dict__["snapshot_every"] = MEMBERS_SNAPSHOT_EVERY
            if "snapshot_max_share" not in self.model_fields_set:
                self.__dict__["snapshot_max_share"] = MEMBERS_SNAPSHOT_SHARE
        return self

    @model_validator(mode="after")
    def _shard_in_range(self) -> WorkerConfig:
        if self.shard >= self.shards:
            raise ValueError(f"shard {self.shard} is not one of shards 0..{self.shards - 1}")
        return self

    def check_served(self, name: str = "worker config") -> WorkerConfig:
        """The ranges a served worker needs beyond the field checks (`occvo serve`, `occvo up`): a cap a worker at
        rest is already over would refuse every stream."""
        if self.max_rss_mb is not None and self.max_rss_mb < MIN_SERVED_RSS_MB:
            raise ConfigError(
                f"{name}: max_rss_mb={self.max_rss_mb} is below {MIN_SERVED_RSS_MB}: a registration worker at rest "
                "uses ~300 MB and new streams are refused over 85% of the cap"
            )
        return self

    @classmethod
    def load(cls, path: str | Path | None, **overrides) -> WorkerConfig:
        from occvo_core import config_file

        data = config_file.read(path) if path is not None else {}
        data.update({k: v for k, v in overrides.items() if v is not None})
        return config_file.validate(cls, data, path or "worker config")
