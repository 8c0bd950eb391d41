"""A run or a followed stream in Foxglove's well-known schemas (foxglove-sdk, the optional `foxglove` extra): written to
an MCAP file, served live over Foxglove's WebSocket protocol, or both. Imported only when one is asked for.

Topics (frame ids as ROS: `map` the odometry's world frame, the first frame's ego; `base_link` the ego):
  /tf           foxglove.FrameTransform  map -> base_link, the current pose
  /trajectory   foxglove.PosesInFrame    the estimated path so far, in map
  /occupancy    foxglove.PointCloud      the frame's occupancy in base_link
  /map          foxglove.PointCloud      the global map in map (every `map_every` frames and at the end; a followed
                                         stream's map after each map update)
Point clouds: x, y, z float32, red, green, blue, alpha uint8 (the class colour), class uint8 (Occ3D id).
Every message is stamped, and logged at, the data's stamp.
"""

from __future__ import annotations

from pathlib import Path

import foxglove
import numpy as np
from foxglove.channels import FrameTransformChannel, PointCloudChannel, PosesInFrameChannel
from foxglove.messages import (
    FrameTransform,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    Pose,
    PosesInFrame,
    Quaternion,
    Timestamp,
    Vector3,
)
from scipy.spatial.transform import Rotation

from occvo_core.grid import CLASS_COLORS
from occvo_core.overwrite import MCAP_METADATA

MAP_FRAME, EGO_FRAME = "map", "base_link"
POINT = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
    + [("class", "u1")]
)
_NUMERIC = {"<f4": PackedElementFieldNumericType.Float32, "|u1": PackedElementFieldNumericType.Uint8}
FIELDS = [
    PackedElementField(name=name, offset=POINT.fields[name][1], type=_NUMERIC[POINT.fields[name][0].str])
    for name in POINT.names
]


REAL_CLOCK_S = 1e8  # stamps past 1973 are wall-clock times; smaller ones are seconds since the scene began


def stamp_ns(stamp: float) -> int:
    """Seconds (a float) to integer nanoseconds. A wall-clock stamp is kept to the microsecond: a float64 of today's
    Unix time holds no finer digit (its step is 0.24 us), and the recorded data's clocks count microseconds."""
    sec = int(np.floor(stamp))
    frac = float(stamp) - sec  # exact: the whole seconds come off without rounding
    if stamp >= REAL_CLOCK_S:
        return sec * 1_000_000_000 + int(round(frac * 1e6)) * 1000
    return sec * 1_000_000_000 + int(round(frac * 1e9))


def _timestamp(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _parts(T: np.ndarray) -> tuple[Vector3, Quaternion]:
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), Quaternion(x=x, y=y, z=z, w=w)


def _pose(T: np.ndarray) -> Pose:
    position, orientation = _parts(T)
    return Pose(position=position, orientation=orientation)


def packed_points(points: np.ndarray, labels: np.ndarray) -> bytes:
    """Points and their classes as POINT records, coloured by class."""
    rec = np.zeros(len(points), POINT)
    for i, axis in enumerate("xyz"):
        rec[axis] = points[:, i]
    colors = CLASS_COLORS[np.asarray(labels, np.int64)]
    rec["red"], rec["green"], rec["blue"], rec["alpha"] = colors[:, 0], colors[:, 1], colors[:, 2], 255
    rec["class"] = labels
    return rec.tobytes()


class FoxgloveView:
    """Logs a run's steps to Foxglove channels of its own context (an MCAP file, a WebSocket server, or both).
    The same calls as RerunView, so a run and StreamFollower log to either."""

    def __init__(
        self, mcap: str | Path | None = None, port: int | None = None, map_every: int = 5, host: str = "127.0.0.1"
    ):
        self.context = foxglove.Context()
        self.map_every = max(1, int(map_every))
        self.writer = self.server = None
        if mcap is not None:
            Path(mcap).parent.mkdir(parents=True, exist_ok=True)
            self.writer = foxglove.open_mcap(str(mcap), allow_overwrite=True, context=self.context)
            # the first record after the header: how occvo tells its own file before replacing it (occvo_core.overwrite)
            self.writer.write_metadata(MCAP_METADATA, {"writer": "occvo"})
        if port is not None:
            self.server = foxglove.start_server(name="occvo", host=host, port=int(port), context=self.context)
        self.tf = FrameTransformChannel("/tf", context=self.context)
        self.trajectory = PosesInFrameChannel("/trajectory", context=self.context)
        self.occupancy_channel = PointCloudChannel("/occupancy", context=self.context)
        self.map_channel = PointCloudChannel("/map", context=self.context)
        self.path: list[Pose] = []
        self.tiles: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.ns = 0  # the stamp of what is logged now
        self._frames = 0

    @property
    def port(self) -> int | None:
        return None if self.server is None else self.server.port

    def time(self, index: int, stamp: float) -> None:
        self.ns = stamp_ns(stamp)

    def pose(self, index: int, stamp: float, pose: np.ndarray) -> None:
        """The ego pose (map -> base_link) and the path so far."""
        self.time(index, stamp)
        T = np.asarray(pose, np.float64)
        self.path.append(_pose(T))
        ts = _timestamp(self.ns)
        translation, rotation = _parts(T)
        self.tf.log(
            FrameTransform(
                timestamp=ts,
                parent_frame_id=MAP_FRAME,
                child_frame_id=EGO_FRAME,
                translation=translation,
                rotation=rotation,
            ),
            log_time=self.ns,
        )
        self.trajectory.log(PosesInFrame(timestamp=ts, frame_id=MAP_FRAME, poses=list(self.path)), log_time=self.ns)

    def _cloud(self, channel, frame_id: str, points: np.ndarray, labels: np.ndarray) -> None:
        channel.log(
            PointCloud(
                timestamp=_timestamp(self.ns),
                frame_id=frame_id,
                pose=_pose(np.eye(4)),
                point_stride=POINT.itemsize,
                fields=FIELDS,
                data=packed_points(np.asarray(points), np.asarray(labels)),
            ),
            log_time=self.ns,
        )

    def occupancy(self, points: np.ndarray, labels: np.ndarray) -> None:
        self._cloud(self.occupancy_channel, EGO_FRAME, points, labels)

    def map(self, points: np.ndarray, labels: np.ndarray) -> None:
        self._cloud(self.map_channel, MAP_FRAME, points, labels)

    def clear_map(self) -> None:
        self.tiles.clear()

    def map_tile(self, ix: int, iy: int, points: np.ndarray, labels: np.ndarray) -> None:
        if len(points):
            self.tiles[(ix, iy)] = (points, labels)
        else:
            self.tiles.pop((ix, iy), None)

    def map_updated(self) -> None:
        """After a followed stream's map update: the map of every tile so far."""
        if self.tiles:
            self.map(*(np.concatenate(parts) for parts in zip(*self.tiles.values())))
        else:
            self.map(np.zeros((0, 3)), np.zeros(0, np.uint8))

    def scalar(self, name: str, value: float) -> None:
        """Counters stay in summary.json and the rerun view; Foxglove's schemas have no scalar."""

    def step(self, frame, result, odometry) -> None:
        self.pose(frame.index, frame.stamp, result.pose)
        self.occupancy(frame.points, frame.labels)
        if self._frames % self.map_every == 0:
            self.map(*odometry.map_points())
        self._frames += 1

    def finish(self, odometry) -> None:
        self.map(*odometry.map_points())
        self.close()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        if self.server is not None:
            self.server.stop()
            self.server = None
