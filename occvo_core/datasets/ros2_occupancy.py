"""Occupancy clouds from a ROS 2 recording (occvo_core/datasets/ros2_recording.py): each `sensor_msgs/PointCloud2` on
the occupancy topic (default /occvo/occupancy) is a frame: x, y, z (float32 or float64) and a class field (Occ3D id,
any integer type), in the ego frame, stamped with its header. Optional beside them: ground truth
(`geometry_msgs/PoseStamped` or `nav_msgs/Odometry` on /occvo/groundtruth, the ego -> world pose at each cloud's
stamp) and the recording's description (`std_msgs/String` JSON on /occvo/source: the scene's name, rate, whether the
ground truth is on the map plane, and the configuration defaults of the source that made the clouds, which a run
takes as it would from that source)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from occvo_core.datasets.ros2_recording import Recording
from occvo_core.errors import DatasetError, InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.recording.messages import cloud_fields, matrix, ns_of_header, stamp_of

OCCUPANCY_TOPIC, GROUNDTRUTH_TOPIC, SOURCE_TOPIC = "/occvo/occupancy", "/occvo/groundtruth", "/occvo/source"
CLASS_FIELDS = ("class", "label")


class RecordedOccupancyScene:
    """SceneSource over a recording's occupancy clouds, in recording order."""

    def __init__(
        self,
        path: str | Path,
        topic: str = OCCUPANCY_TOPIC,
        gt_topic: str = GROUNDTRUTH_TOPIC,
        source_topic: str = SOURCE_TOPIC,
    ):
        self.path, self.topic = Path(path), topic
        rec = Recording(path, [topic, gt_topic, source_topic], {topic: "--occupancy-topic"})
        rec.expect(topic, "sensor_msgs/msg/PointCloud2")
        rec.expect(gt_topic, "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")
        rec.expect(source_topic, "std_msgs/msg/String")
        self.recording = rec
        if not rec.messages[topic]:
            raise DatasetError(self.path, f"topic {topic} holds no message")
        info = rec.decoded(source_topic)
        self.info = json.loads(info[-1].data) if info else {}
        self.name = self.info.get("name", self.path.stem)
        self.rate_hz = float(self.info.get("rate_hz", 2.0))
        self.gt_on_map_plane = bool(self.info.get("gt_on_map_plane", False))
        if self.info.get("config_defaults"):
            self.config_defaults = self.info["config_defaults"]
        self.stamp_ns = [ns_of_header(m.header) for m in (rec.decode(topic, i) for i in range(len(self)))]
        self._gt = self._groundtruth(rec.decoded(gt_topic))

    def __len__(self) -> int:
        return len(self.recording.messages[self.topic])

    @property
    def stamps(self) -> np.ndarray:
        return np.array([stamp_of(ns) for ns in self.stamp_ns])

    @property
    def gt_poses(self) -> np.ndarray | None:
        return self._gt

    def _groundtruth(self, msgs: list) -> np.ndarray | None:
        """A pose for every cloud, matched by stamp; None when any is missing."""
        by_ns = {}
        for m in msgs:
            pose = m.pose.pose if hasattr(m, "child_frame_id") else m.pose
            by_ns[ns_of_header(m.header)] = matrix(pose.position, pose.orientation)
        if not by_ns or any(ns not in by_ns for ns in self.stamp_ns):
            return None
        return np.array([by_ns[ns] for ns in self.stamp_ns])

    def __getitem__(self, index: int) -> OccupancyFrame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        where = f"{index} ({self.path} {self.topic})"
        msg = self.recording.decode(self.topic, index)
        names = [f.name for f in msg.fields]
        label = next((n for n in CLASS_FIELDS if n in names), CLASS_FIELDS[0])
        try:
            x, y, z, labels = cloud_fields(msg, ("x", "y", "z", label), f"frame {where}")
        except ValueError as exc:
            raise InvalidFrameError(where, str(exc).split(": ", 1)[1]) from None
        points = np.column_stack([x, y, z]).astype(np.float64)
        if labels.size and (labels.min() < 0 or labels.max() > 255):
            raise InvalidFrameError(where, f"classes outside 0..17: min {labels.min()}, max {labels.max()}")
        frame = OccupancyFrame(points, labels.astype(np.uint8), index, stamp_of(self.stamp_ns[index]))
        frame.meta.update(scene=self.name, source="recording")
        try:
            return frame.validate()
        except InvalidFrameError as exc:
            raise InvalidFrameError(where, exc.reason) from None
