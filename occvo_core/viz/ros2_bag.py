"""A run as a ROS 2 bag, written with rosbags (the optional `ros` extra; no ROS install), so `ros2 bag play` feeds
RViz and fusion stacks (robot_localization). Imported only when a bag is asked for. Topics as the live node names
them; frames as REP 105 (names configurable):

  /occvo/odom       nav_msgs/msg/Odometry        odom -> base_link, pose covariance from fine GICP's information
                                                 (registration/pose_covariance.py), twist from consecutive poses
                                                 with its covariance
  /tf               tf2_msgs/msg/TFMessage       map -> odom (loop closures move it) and odom -> base_link
  /occvo/path       nav_msgs/msg/Path            the last PATH_WINDOW poses in map (a bounded window: the bag grows
                                                 linearly with the drive), and the whole path once at the end
  /occvo/occupancy  sensor_msgs/msg/PointCloud2  the frame's occupancy in base_link
  /occvo/map        sensor_msgs/msg/PointCloud2  the map in map: within 40 m of the ego every `map_every` frames
                                                 (viz/near_map.py), the whole map at the end; offered transient local
                                                 (latched) in the bag's QoS metadata
Point clouds: x, y, z float32, rgb float32 (RViz's packed 0x00RRGGBB, the class colour), class uint8 (Occ3D id).
Every message is stamped, and recorded at, the data's stamp. The bag version is the distribution's
(occvo_core/recording/writer.py: Humble 5, Jazzy 8), sqlite3 storage.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occvo_core.grid import CLASS_COLORS
from occvo_core.recording import messages as m
from occvo_core.recording.writer import RecordingWriter
from occvo_core.viz.foxglove_log import stamp_ns
from occvo_core.viz.near_map import map_near
from occvo_core.viz.odom_frames import FrameNames, OdomFrames

STORE = m.typestore("jazzy")  # the message definitions are the same in Humble's for every type here
POINT = np.dtype(
    {"names": ["x", "y", "z", "rgb", "class"], "formats": ["<f4", "<f4", "<f4", "<u4", "u1"], "itemsize": 20}
)
FIELD_TYPES = {"x": "FLOAT32", "y": "FLOAT32", "z": "FLOAT32", "rgb": "FLOAT32", "class": "UINT8"}
TOPICS = {
    "/occvo/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/occvo/path": "nav_msgs/msg/Path",
    "/occvo/occupancy": "sensor_msgs/msg/PointCloud2",
    "/occvo/map": "sensor_msgs/msg/PointCloud2",
}
LATCHED = {"/occvo/map"}
PATH_WINDOW = 100


def point_cloud(store, ns: int, frame_id: str, points: np.ndarray, labels: np.ndarray):
    rec = np.zeros(len(points), POINT)
    for i, axis in enumerate("xyz"):
        rec[axis] = points[:, i]
    c = CLASS_COLORS[np.asarray(labels, np.int64)].astype(np.uint32)
    rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]  # read as float32 bits, as RViz does
    rec["class"] = labels
    return m.cloud_msg(store, ns, frame_id, rec, FIELD_TYPES)


class Ros2Bag:
    """Writes a run's steps to a ROS 2 bag at `path`, a folder that must not exist yet."""

    def __init__(self, path: str | Path, map_every: int = 5, distro: str = "jazzy", frames: FrameNames = FrameNames()):
        self.writer = RecordingWriter(path, distro=distro, storage="sqlite3", flag="--ros2-bag")
        self.store, self.frames = self.writer.store, frames
        for topic, kind in TOPICS.items():
            self.writer.add(topic, kind, latched=topic in LATCHED)
        self.map_every = max(1, int(map_every))
        self.odom = OdomFrames()
        self.path: list = []
        self._frames = 0

    def _write(self, topic: str, ns: int, msg) -> None:
        self.writer.write(topic, ns, msg)

    def pose(self, ns: int, pose: np.ndarray, covariance=None, loop_correction=None) -> None:
        T, f = self.store.types, self.frames
        odom, pose_cov, (linear, angular), twist_cov = self.odom.update(pose, ns, covariance, loop_correction)
        vec = T["geometry_msgs/msg/Vector3"]
        self._write(
            "/occvo/odom",
            ns,
            T["nav_msgs/msg/Odometry"](
                header=m.header(self.store, ns, f.odom),
                child_frame_id=f.base,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=m.pose_msg(self.store, odom), covariance=pose_cov.reshape(36)
                ),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](
                        linear=vec(*map(float, linear)), angular=vec(*map(float, angular))
                    ),
                    covariance=twist_cov.reshape(36),
                ),
            ),
        )
        stamped = T["geometry_msgs/msg/TransformStamped"]
        tf = [
            stamped(
                header=m.header(self.store, ns, f.map),
                child_frame_id=f.odom,
                transform=m.transform_msg(self.store, self.odom.map_to_odom),
            ),
            stamped(
                header=m.header(self.store, ns, f.odom),
                child_frame_id=f.base,
                transform=m.transform_msg(self.store, odom),
            ),
        ]
        self._write("/tf", ns, T["tf2_msgs/msg/TFMessage"](transforms=tf))
        self.path.append(
            T["geometry_msgs/msg/PoseStamped"](
                header=m.header(self.store, ns, f.map), pose=m.pose_msg(self.store, pose)
            )
        )
        window = self.path[-PATH_WINDOW:]
        self._write("/occvo/path", ns, T["nav_msgs/msg/Path"](header=m.header(self.store, ns, f.map), poses=window))

    def step(self, frame, result, odometry) -> None:
        ns = stamp_ns(frame.stamp)
        self.pose(ns, result.pose, getattr(result, "covariance", None), getattr(result, "loop_correction", None))
        self._write("/occvo/occupancy", ns, point_cloud(self.store, ns, self.frames.base, frame.points, frame.labels))
        if self._frames % self.map_every == 0:
            near = map_near(odometry, result.pose)
            self._write("/occvo/map", ns, point_cloud(self.store, ns, self.frames.map, *near))
        self._frames += 1
        self._ns = ns

    def finish(self, odometry) -> None:
        if self._frames:
            T, f = self.store.types, self.frames
            self._write("/occvo/map", self._ns, point_cloud(self.store, self._ns, f.map, *odometry.map_points()))
            if len(self.path) > PATH_WINDOW:  # the whole path, once
                whole = T["nav_msgs/msg/Path"](header=m.header(self.store, self._ns, f.map), poses=self.path)
                self._write("/occvo/path", self._ns, whole)
        self.close()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def abandon(self) -> None:
        if self.writer is not None:
            self.writer.abandon()
            self.writer = None
