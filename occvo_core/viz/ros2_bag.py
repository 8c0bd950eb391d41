"""A run as a ROS 2 bag, written with rosbags (the optional `ros` extra; no ROS install), so `ros2 bag play` feeds
RViz. Imported only when a bag is asked for.

Topics (frame ids: `map` the odometry's world frame, the first frame's ego; `base_link` the ego):
  /odom        nav_msgs/msg/Odometry         the pose of each frame, map -> base_link
  /tf          tf2_msgs/msg/TFMessage        the same transform
  /path        nav_msgs/msg/Path             the estimated path so far
  /occupancy   sensor_msgs/msg/PointCloud2   the frame's occupancy in base_link
  /map         sensor_msgs/msg/PointCloud2   the global map in map (every `map_every` frames and at the end)
Point clouds: x, y, z float32, rgb float32 (RViz's packed 0x00RRGGBB, the class colour), class uint8 (Occ3D id).
Every message is stamped, and recorded at, the data's stamp.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from occvo_core.errors import ConfigError
from occvo_core.grid import CLASS_COLORS
from occvo_core.viz.foxglove_log import EGO_FRAME, MAP_FRAME, stamp_ns

STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types
POINT = np.dtype(
    {"names": ["x", "y", "z", "rgb", "class"], "formats": ["<f4", "<f4", "<f4", "<u4", "u1"], "itemsize": 20}
)
FIELD_TYPES = {"x": "FLOAT32", "y": "FLOAT32", "z": "FLOAT32", "rgb": "FLOAT32", "class": "UINT8"}
TOPICS = {
    "/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/path": "nav_msgs/msg/Path",
    "/occupancy": "sensor_msgs/msg/PointCloud2",
    "/map": "sensor_msgs/msg/PointCloud2",
}


def _header(ns: int, frame_id: str):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id
    )


def _pose(M: np.ndarray):
    x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat()
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def point_cloud(ns: int, frame_id: str, points: np.ndarray, labels: np.ndarray):
    rec = np.zeros(len(points), POINT)
    for i, axis in enumerate("xyz"):
        rec[axis] = points[:, i]
    c = CLASS_COLORS[np.asarray(labels, np.int64)].astype(np.uint32)
    rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]  # read as float32 bits, as RViz does
    rec["class"] = labels
    field = T["sensor_msgs/msg/PointField"]
    fields = [
        field(name=n, offset=POINT.fields[n][1], datatype=getattr(field, FIELD_TYPES[n]), count=1) for n in POINT.names
    ]
    return T["sensor_msgs/msg/PointCloud2"](
        header=_header(ns, frame_id),
        height=1,
        width=len(rec),
        fields=fields,
        is_bigendian=False,
        point_step=POINT.itemsize,
        row_step=POINT.itemsize * len(rec),
        data=np.frombuffer(rec.tobytes(), np.uint8),
        is_dense=True,
    )


class Ros2Bag:
    """Writes a run's steps to a ROS 2 bag (sqlite3 storage) at `path`, a folder that must not exist yet."""

    def __init__(self, path: str | Path, map_every: int = 5):
        path = Path(path)
        if path.exists():
            raise ConfigError(f"--ros2-bag {path}: already exists (a bag is a new folder): remove it or name another")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.writer = Writer(path, version=8)
        self.writer.open()
        self.conn = {topic: self.writer.add_connection(topic, kind, typestore=STORE) for topic, kind in TOPICS.items()}
        self.map_every = max(1, int(map_every))
        self.path: list = []
        self._frames = 0

    def _write(self, topic: str, ns: int, msg) -> None:
        self.writer.write(self.conn[topic], ns, STORE.serialize_cdr(msg, TOPICS[topic]))

    def pose(self, ns: int, pose: np.ndarray) -> None:
        M = np.asarray(pose, np.float64)
        p = _pose(M)
        zero6 = np.zeros(36)  # no covariance estimate: zeros, as an unknown covariance is commonly sent
        twist = T["geometry_msgs/msg/Twist"](
            linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        )
        self._write(
            "/odom",
            ns,
            T["nav_msgs/msg/Odometry"](
                header=_header(ns, MAP_FRAME),
                child_frame_id=EGO_FRAME,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=zero6),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zero6.copy()),
            ),
        )
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]), rotation=p.orientation
        )
        self._write(
            "/tf",
            ns,
            T["tf2_msgs/msg/TFMessage"](
                transforms=[
                    T["geometry_msgs/msg/TransformStamped"](
                        header=_header(ns, MAP_FRAME), child_frame_id=EGO_FRAME, transform=transform
                    )
                ]
            ),
        )
        self.path.append(T["geometry_msgs/msg/PoseStamped"](header=_header(ns, MAP_FRAME), pose=p))
        self._write("/path", ns, T["nav_msgs/msg/Path"](header=_header(ns, MAP_FRAME), poses=list(self.path)))

    def step(self, frame, result, odometry) -> None:
        ns = stamp_ns(frame.stamp)
        self.pose(ns, result.pose)
        self._write("/occupancy", ns, point_cloud(ns, EGO_FRAME, frame.points, frame.labels))
        if self._frames % self.map_every == 0:
            self._write("/map", ns, point_cloud(ns, MAP_FRAME, *odometry.map_points()))
        self._frames += 1
        self._ns = ns

    def finish(self, odometry) -> None:
        if self._frames:
            self._write("/map", self._ns, point_cloud(self._ns, MAP_FRAME, *odometry.map_points()))
        self.close()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
