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

from occvo_core.errors import ConfigError
from occvo_core.viz import ros_messages as rm
from occvo_core.viz.foxglove_log import EGO_FRAME, MAP_FRAME, stamp_ns
from occvo_core.viz.ros_messages import STORE, T, point_cloud

TOPICS = {
    "/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/path": "nav_msgs/msg/Path",
    "/occupancy": "sensor_msgs/msg/PointCloud2",
    "/map": "sensor_msgs/msg/PointCloud2",
}


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
        self._write("/odom", ns, rm.odometry(ns, M, MAP_FRAME, EGO_FRAME))
        self._write("/tf", ns, rm.transform(ns, M, MAP_FRAME, EGO_FRAME))
        self.path.append(rm.pose_stamped(ns, M, MAP_FRAME))
        self._write("/path", ns, T["nav_msgs/msg/Path"](header=self.path[-1].header, poses=list(self.path)))

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
