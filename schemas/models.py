"""Every message occvo sends over Zenoh, as pydantic v2 models.

Each message carries `kind` (which model) and `schema_version`; the codec (schemas/codec.py) checks both before
validating. Numpy arrays travel as `Array` (dtype, shape, raw little-endian bytes) so msgpack carries them as `bin`.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from occvo_core.grid import NUM_CLASSES, GridSpec

SCHEMA_VERSION = 1  # every kind's first version; VERSIONS (below) holds each kind's newest
ALLOWED_DTYPES = ("uint8", "uint16", "int32", "int64", "float32", "float64")
Finite = Annotated[float, Field(allow_inf_nan=False)]
# validation context: a SparseOccupancy's arrays checked for dtype, shape and size only, not voxel by voxel (a worker
# that forwards it unread: the one that uses its voxels checks them, e.g. the inference worker's replay source)
SHAPES_ONLY = "occupancy_shapes_only"
SEQ_LIMIT = 2**63  # seq is a signed 64-bit integer in the store and in Trajectory.seqs: 0 <= seq < 2^63


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=False, arbitrary_types_allowed=False)


class Array(_Model):
    """An n-d numpy array: dtype name, shape, and the C-order little-endian bytes."""

    dtype: Literal["uint8", "uint16", "int32", "int64", "float32", "float64"]
    shape: list[Annotated[int, Field(ge=0)]]
    data: bytes

    @model_validator(mode="after")
    def _size_matches(self) -> Array:
        itemsize = np.dtype(self.dtype).itemsize
        if len(self.shape) > 32 or math.prod(d for d in self.shape if d) * itemsize >= 2**63:  # numpy could not hold it
            raise ValueError(f"array shape {self.shape} is too large for numpy, even with no elements")
        expected = math.prod(self.shape) * itemsize  # Python ints: a huge shape cannot wrap to 0
        if len(self.data) != expected:
            raise ValueError(
                f"array of dtype {self.dtype} and shape {self.shape} needs {expected} bytes, got {len(self.data)}"
            )
        return self

    @classmethod
    def from_numpy(cls, a: np.ndarray) -> Array:
        a = np.asarray(a)
        if a.dtype.name not in ALLOWED_DTYPES:
            raise ValueError(f"dtype {a.dtype} cannot travel; use one of {ALLOWED_DTYPES}")
        a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
        return cls(dtype=a.dtype.name, shape=list(a.shape), data=a.tobytes())

    def to_numpy(self) -> np.ndarray:
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype).newbyteorder("<")).reshape(self.shape)


class GridSpecModel(_Model):
    lower: tuple[Finite, Finite, Finite] = (-40.0, -40.0, -1.0)
    upper: tuple[Finite, Finite, Finite] = (40.0, 40.0, 5.4)
    voxel_size: Finite = Field(0.4, gt=0)

    @model_validator(mode="after")
    def _extent(self) -> GridSpecModel:
        n = [(u - l) / self.voxel_size for l, u in zip(self.lower, self.upper)]
        if not all(0.5 <= x <= 65536 for x in n):  # also catches inf and NaN; indices travel as uint16 at most
            raise ValueError(
                f"grid {self.lower}..{self.upper} of {self.voxel_size} m voxels must span 1..65536 voxels per axis"
            )
        return self

    def to_grid(self) -> GridSpec:
        return GridSpec(tuple(self.lower), tuple(self.upper), self.voxel_size)

    @classmethod
    def from_grid(cls, g: GridSpec) -> GridSpecModel:
        return cls(lower=tuple(g.lower), upper=tuple(g.upper), voxel_size=g.voxel_size)


def _col_extremes(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column min and max of an (N,3) array; column by column is ~10x faster than axis=0 here."""
    return np.array([a[:, i].min() for i in range(a.shape[1])]), np.array([a[:, i].max() for i in range(a.shape[1])])


def _duplicates(v: np.ndarray, shape: tuple[int, int, int] | None) -> int:
    """Rows of v (N,3) repeating an earlier row: voxel indices (`shape`: the grid's) or coordinates (None)."""
    if shape is not None and math.prod(shape) <= 1 << 24:  # a flag per grid cell: one pass, no sort, no counts
        c = v.astype(np.int32)  # under 2^24 cells: int32 holds every cell number
        lin = (c[:, 0] * shape[1] + c[:, 1]) * shape[2] + c[:, 2]
        if (lin[1:] > lin[:-1]).all():  # cells rising in grid order (replays, the network's output): none twice
            return 0
        seen = np.zeros(math.prod(shape), np.bool_)
        seen[lin] = True
        return int(len(v) - np.count_nonzero(seen))
    rows = np.ascontiguousarray(v).view(np.dtype((np.void, v.dtype.itemsize * 3))).ravel()
    return int(len(v) - len(np.unique(rows)))


def _check_axes(axes: Array, grid: GridSpec) -> None:
    """SparseOccupancy.axes (its shape checked): one finite coordinate an index, inside the grid."""
    a = axes.to_numpy()
    inside = (a >= np.array(grid.lower)[:, None]) & (a < np.array(grid.upper)[:, None])  # NaN fails both
    for k, n in enumerate(grid.shape):
        if not inside[k, :n].all():
            raise ValueError(
                f"axes: {int((~inside[k, :n]).sum())} coordinates of axis {k} outside the grid or not finite"
            )


class SparseOccupancy(_Model):
    """Occupied voxels of one grid with their labels (N,). Voxels travel either as integer indices (N,3) on the grid
    (compact: 4 bytes a voxel; network output) or as exact float64 ego-frame coordinates (N,3). Recorded data holds
    voxel centres only to within rounding, and a replay must reproduce an offline run bit for bit: such a frame
    travels as indices with `axes`, each index's exact coordinate along each axis (GridSpec.axis_tables), or, when
    its coordinates are not one per index, as points. Exactly one of `voxels` and `points` is set."""

    grid: GridSpecModel = GridSpecModel()
    voxels: Array | None = Field(None, description="(N,3) uint8 or uint16 voxel indices i, j, k on the grid")
    axes: Array | None = Field(
        None,
        description="(3, K) float64, K the grid's largest dimension, with voxels only: row a holds the coordinate "
        "of each index along axis a (none given: the voxel centres)",
    )
    points: Array | None = Field(None, description="(N,3) float64 ego-frame voxel coordinates, inside the grid")
    labels: Array = Field(description="(N,) uint8 Occ3D class ids 0..17")

    @model_validator(mode="after")
    def _check(self, info: ValidationInfo) -> SparseOccupancy:
        grid = self.grid.to_grid()
        n = self._check_shapes(grid)
        if not (info.context and info.context.get(SHAPES_ONLY)):
            self._check_voxels(grid, n)
        return self

    def _check_shapes(self, grid: GridSpec) -> int:
        """The arrays' dtypes and shapes, one label a voxel, no more voxels than cells: the voxel count."""
        if (self.voxels is None) == (self.points is None):
            raise ValueError("set exactly one of voxels (grid indices) and points (coordinates)")
        if self.voxels is not None:
            v = self.voxels
            if v.dtype not in ("uint8", "uint16") or len(v.shape) != 2 or v.shape[1] != 3:
                raise ValueError(f"voxels must be (N,3) uint8/uint16, got {v.dtype} {v.shape}")
            axes = self.axes
            if axes is not None and (axes.dtype != "float64" or axes.shape != [3, max(grid.shape)]):
                raise ValueError(f"axes must be (3, {max(grid.shape)}) float64, got {axes.dtype} {axes.shape}")
        else:
            if self.axes is not None:
                raise ValueError("axes come with voxels (indices), not with points")
            v = self.points
            if v.dtype != "float64" or len(v.shape) != 2 or v.shape[1] != 3:
                raise ValueError(f"points must be (N,3) float64, got {v.dtype} {v.shape}")
        n, l = v.shape[0], self.labels
        if l.dtype != "uint8" or len(l.shape) != 1 or l.shape[0] != n:
            raise ValueError(f"labels must be ({n},) uint8, got {l.dtype} {l.shape}")
        cells = math.prod(grid.shape)
        if n > cells:
            raise ValueError(f"{n} voxels, more than the grid's {cells} cells {tuple(grid.shape)}")
        return n

    def _check_voxels(self, grid: GridSpec, n: int) -> None:
        """Each voxel inside the grid (finite), none twice, each label a class."""
        if self.voxels is not None:
            v = self.voxels.to_numpy()
            top = np.array([v[:, i].max() for i in range(3)]) if n else None  # unsigned: their maxima are enough
            if n and (top >= np.array(grid.shape)).any():  # one pass on the happy path
                over = np.any(v >= np.array(grid.shape), axis=1)
                raise ValueError(f"{int(over.sum())} voxel indices outside the grid shape {grid.shape}")
            if self.axes is not None:
                _check_axes(self.axes, grid)
        else:
            v = self.points.to_numpy()
            if n:
                lo, hi = _col_extremes(v)  # NaN and inf show in the extremes: one pass when all is well
                if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
                    bad = ~np.isfinite(v).all(axis=1)
                    raise ValueError(f"{int(bad.sum())} points with non-finite coordinates (NaN or inf)")
                if (lo < np.array(grid.lower)).any() or (hi >= np.array(grid.upper)).any():
                    out = ~grid.inside(grid.indices_of(v))
                    raise ValueError(f"{int(out.sum())} points outside the grid {grid.lower}..{grid.upper}")
        # a frame is a set of voxels: at most one a grid cell, none twice (3.5 M copies of one voxel passed every
        # size check and took registration past its memory cap)
        if n > 1:
            dup = _duplicates(v, tuple(grid.shape) if self.voxels is not None else None)
            if dup:
                raise ValueError(f"{dup} duplicate voxels: a frame is a set of voxels, each once")
        if n:
            top = int(self.labels.to_numpy().max())
            if top >= NUM_CLASSES:
                raise ValueError(f"labels out of range 0..{NUM_CLASSES - 1}: max {top}")

    @classmethod
    def from_points(cls, points: np.ndarray, labels: np.ndarray, grid: GridSpec, exact: bool = True) -> SparseOccupancy:
        """exact: the coordinates bit for bit (as indices with axes where they allow it); else snapped to voxel
        indices (compact)."""
        labels = Array.from_numpy(np.asarray(labels, dtype=np.uint8))
        dtype = np.uint8 if max(grid.shape) <= 256 else np.uint16
        if exact:
            tables = grid.axis_tables(points)
            if tables is not None:
                idx, axes = tables
                voxels, axes = Array.from_numpy(idx.astype(dtype)), Array.from_numpy(axes)
                return cls(grid=GridSpecModel.from_grid(grid), voxels=voxels, axes=axes, labels=labels)
            return cls(
                grid=GridSpecModel.from_grid(grid),
                points=Array.from_numpy(np.asarray(points, np.float64)),
                labels=labels,
            )
        idx = grid.indices_of(points)
        if len(idx) and not grid.inside(idx).all():
            raise ValueError(f"{int((~grid.inside(idx)).sum())} points fall outside the grid")
        return cls(grid=GridSpecModel.from_grid(grid), voxels=Array.from_numpy(idx.astype(dtype)), labels=labels)

    def to_points(self) -> np.ndarray:
        """Ego-frame coordinates (N,3) float64: as sent, or the voxel centres of the indices."""
        if self.points is not None:
            return self.points.to_numpy().copy()
        idx = self.voxels.to_numpy()
        if self.axes is not None:
            return GridSpec.points_of(idx, self.axes.to_numpy())
        return self.grid.to_grid().centres_of(idx.astype(np.int64))

    def index_tables(self, grid: GridSpec) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(indices, axes or None for the centres) as sent, when the voxels came as indices on `grid`; else None."""
        if self.voxels is None or self.grid.to_grid() != grid:
            return None
        return self.voxels.to_numpy(), None if self.axes is None else self.axes.to_numpy()

    def __len__(self) -> int:
        return self.labels.shape[0]


class _Message(_Model):
    schema_version: int = SCHEMA_VERSION


class _StreamMessage(_Message):
    stream: str = Field(pattern=r"^[A-Za-z0-9_\-.]{1,64}$", description="stream id, one key chunk")


def _finite_matrix(m: list[list[float]], rows: int, cols: int, what: str) -> list[list[float]]:
    if len(m) != rows or any(len(r) != cols for r in m):
        raise ValueError(f"{what} must be {rows}x{cols}")
    if not all(math.isfinite(x) for r in m for x in r):
        raise ValueError(f"{what} has non-finite values (NaN or inf)")
    return m


class CameraImage(_Model):
    camera: str = Field(description="e.g. CAM_FRONT")
    encoding: Literal["jpeg", "png", "raw_rgb8"]
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)
    data: bytes
    intrinsics: list[list[float]] = Field(description="3x3 pinhole K")
    extrinsics: list[list[float]] = Field(description="4x4 camera-to-ego")
    stamp: Finite | None = Field(
        None,
        description="this image's own capture time (s), where the cameras are not "
        "triggered together (nuScenes); the frame's stamp otherwise",
    )

    @field_validator("intrinsics")
    @classmethod
    def _k(cls, v):
        return _finite_matrix(v, 3, 3, "intrinsics")

    @field_validator("extrinsics")
    @classmethod
    def _t(cls, v):
        return _finite_matrix(v, 4, 4, "extrinsics")

    @model_validator(mode="after")
    def _raw_size(self) -> CameraImage:
        if self.encoding == "raw_rgb8" and len(self.data) != self.width * self.height * 3:
            raise ValueError(
                f"raw_rgb8 image {self.camera} needs {self.width * self.height * 3} bytes, got {len(self.data)}"
            )
        return self


class CameraFrame(_StreamMessage):
    """The six camera images of one instant. A recorded frame may carry its ground-truth occupancy instead of,
    or besides, the images: the `replay` inference source uses it (the paper's ground-truth occupancy row)."""

    kind: Literal["camera_frame"] = "camera_frame"
    seq: int = Field(ge=0, lt=SEQ_LIMIT, description="0 starts a new trajectory")
    stamp: Finite
    images: list[CameraImage] = Field(default_factory=list, description="0 or 6 images")
    gt_occupancy: SparseOccupancy | None = None
    sent_at: Finite = Field(0.0, description="publisher wall clock, seconds, for hop latency")

    @field_validator("images")
    @classmethod
    def _six(cls, v):
        if len(v) not in (0, 6):
            raise ValueError(f"a camera frame has 6 images (or none for occupancy-only replay), got {len(v)}")
        return v


class OccupancyFrameMsg(_StreamMessage):
    kind: Literal["occupancy_frame"] = "occupancy_frame"
    seq: int = Field(ge=0, lt=SEQ_LIMIT)
    stamp: Finite
    source: str = Field(description="replay | model:<name>")
    occupancy: SparseOccupancy
    timings_ms: dict[str, Finite] = Field(default_factory=dict, description="upstream stage timings")
    sent_at: Finite = 0.0


Status = Literal[
    "ok", "lost", "initialised", "reinitialised", "relocalised", "degenerate"
]  # initialised: a trajectory's first pose (version 1 called it reinitialised). relocalised: a loop closed; replaces
# the seq's earlier pose. degenerate: too few or collinear voxels to register, the pose a constant-velocity guess


class PoseEstimate(_StreamMessage):
    """Version 2, on occvo/<stream>/pose/v2: a trajectory's first pose is `initialised` (as offline OccVO names it)
    and a registered pose carries its covariance. Version 1 (schemas/pose_v1.py) goes on on occvo/<stream>/pose for
    clients built before: its closed status list and extra="forbid" refuse both changes."""

    kind: Literal["pose_estimate"] = "pose_estimate"
    schema_version: int = 2
    seq: int = Field(ge=0, lt=SEQ_LIMIT)
    stamp: Finite
    pose: list[list[float]] = Field(description="4x4 ego-to-world, first frame of a trajectory = identity")
    status: Status
    timings_ms: dict[str, Finite] = Field(
        default_factory=dict, description="per-stage timings, inference to registration"
    )
    sent_at: Finite = 0.0
    covariance: list[list[float]] | None = Field(
        None,
        description="6x6 covariance of the pose, (rotation, translation) in the ego frame, from fine GICP's "
        "information matrix (docs/design.md); zeros for a trajectory's first pose; none where registration did not "
        "fix the pose (degenerate, relocalised)",
    )

    @field_validator("pose")
    @classmethod
    def _p(cls, v):
        return _finite_matrix(v, 4, 4, "pose")

    @field_validator("covariance")
    @classmethod
    def _c(cls, v):
        return None if v is None else _finite_matrix(v, 6, 6, "covariance")

    def matrix(self) -> np.ndarray:
        return np.array(self.pose, dtype=np.float64)


class Trajectory(_StreamMessage):
    kind: Literal["trajectory"] = "trajectory"
    seqs: Array = Field(description="(T,) int64")
    stamps: Array = Field(description="(T,) float64")
    poses: Array = Field(description="(T,4,4) float64")


class MapTileQuery(_StreamMessage):
    """Optional query payload; without it the tile indices come from the key (a wildcard key asks for a region)."""

    kind: Literal["map_tile_query"] = "map_tile_query"
    ix_min: int | None = None
    ix_max: int | None = None
    iy_min: int | None = None
    iy_max: int | None = None
    page: int = Field(0, ge=0, description="a region is answered max_query_tiles tiles at a time: which of them")


class MapTile(_StreamMessage):
    kind: Literal["map_tile"] = "map_tile"
    ix: int
    iy: int
    tile_m: Finite = Field(gt=0)
    seq: int = Field(ge=0, lt=SEQ_LIMIT, description="frame whose registration last changed the tile")
    points: Array = Field(description="(M,3) float64 world-frame voxel centres")
    labels: Array = Field(description="(M,) uint8")

    @model_validator(mode="after")
    def _check(self) -> MapTile:
        if self.points.dtype != "float64" or len(self.points.shape) != 2 or self.points.shape[1] != 3:
            raise ValueError(f"tile points must be (M,3) float64, got {self.points.dtype} {self.points.shape}")
        if self.labels.dtype != "uint8" or self.labels.shape != [self.points.shape[0]]:
            raise ValueError(f"tile labels must be ({self.points.shape[0]},) uint8")
        if not np.all(np.isfinite(self.points.to_numpy())):
            raise ValueError("tile points have non-finite values")
        return self

    def extent(self) -> tuple[list[float], list[float]]:
        """Per-axis min and max of the points (the map store's bounds of the tile)."""
        lo, hi = _col_extremes(self.points.to_numpy())
        return lo.tolist(), hi.tolist()


class MapUpdate(_StreamMessage):
    """Registration worker -> map service after each frame: the tiles that changed (empty points = tile removed)."""

    kind: Literal["map_update"] = "map_update"
    seq: int = Field(ge=0, lt=SEQ_LIMIT)
    reset: bool = Field(False, description="a new trajectory started: drop every tile of the stream first")
    tile_m: Finite = Field(gt=0)
    tiles: list[MapTile] = Field(default_factory=list)


class MapInfo(_StreamMessage):
    kind: Literal["map_info"] = "map_info"
    tile_m: Finite
    tile_count: int
    voxel_count: int
    last_seq: int | None
    bounds_min: tuple[Finite, Finite, Finite] | None
    bounds_max: tuple[Finite, Finite, Finite] | None
    tiles: list[tuple[int, int]] = Field(default_factory=list)


ErrorCode = Literal[
    "malformed",
    "unknown_kind",
    "unsupported_version",
    "invalid_message",
    "oversize",
    "stream_mismatch",
    "out_of_order",
    "missing_seq",
    "invalid_frame",
    "tile_not_found",
    "bad_query",
    "internal",
    "seq_jump",
    "stream_limit",  # a seq beyond the stream's window (not adopted); a worker's or client's streams full
    "truncated",  # a region's page is full: more tiles on the next page
    "busy",  # the querying client has max_queries_per_client queries in work: ask again when one is answered
    "not_owner",  # a frame from another client than the one its stream is bound to (no seq: not its owner's answer)
    "seq_held",  # a jump held until the frame after it confirms it: not an answer yet (the client waits, resends)
    "not_stored",  # the store refused the write (e.g. disk full): not an answer yet (the client resends it)
    "store_quota",  # the client's streams or bytes in the store are at its quota: the frame is not registered
    "store_unavailable",  # the store cannot be reached and the worker cannot hold the frame: not an answer (resent)
    "stream_full",  # lossless: the stream's queue is full (or a frame before it was turned away): not an answer (resent)
]


class ErrorEvent(_Message):
    kind: Literal["error_event"] = "error_event"
    stream: str = Field(description="stream of the offending key, or '*'")
    worker: str
    code: ErrorCode
    message: str
    key: str = ""
    seq: int | None = None
    stamp: Finite = 0.0


class StageStats(_Model):
    count: int
    p50_ms: Finite
    p90_ms: Finite
    p99_ms: Finite
    mean_ms: Finite


class WorkerHealth(_Message):
    kind: Literal["worker_health"] = "worker_health"
    worker: str
    role: Literal["inference", "registration", "map"]
    pid: int
    uptime_s: Finite
    policy: Literal["lossless", "latest"]
    streams: list[str]
    counters: dict[str, int] = Field(description="frames_in, frames_out, drops, errors, ...")
    queue_depth: dict[str, int] = Field(default_factory=dict)
    stages: dict[str, StageStats] = Field(default_factory=dict)


MESSAGES: dict[str, type[_Message]] = {
    m.model_fields["kind"].default: m
    for m in (
        CameraFrame,
        OccupancyFrameMsg,
        PoseEstimate,
        Trajectory,
        MapTileQuery,
        MapTile,
        MapUpdate,
        MapInfo,
        ErrorEvent,
        WorkerHealth,
    )
}
# each kind's newest version: what this build sends and the newest it reads (older ones read as the newest model)
VERSIONS: dict[str, int] = {kind: m.model_fields["schema_version"].default for kind, m in MESSAGES.items()}
