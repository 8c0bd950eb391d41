"""Six cameras from a ROS 2 recording (occvo_core/datasets/ros2_recording.py), as nuscenes2mcap records a drive:
per camera `sensor_msgs/CompressedImage` on /<CAMERA>/image_rect_compressed and `sensor_msgs/CameraInfo` on
/<CAMERA>/camera_info (topic templates with {camera}), the cameras' extrinsics on /tf_static (base_link -> the
camera's frame id). Keyframe i is the i-th image of every camera. It offers what a nuScenes drive offers the camera
model (occvo_core/models/image_source.py's NuScenesImageSource): `rig(i)`, keyframes with their images as `files`
(in memory) and a stamp, ground truth when the recording has it (/occvo/groundtruth, one pose a keyframe: its
stamps are the keyframes'; without it, CAM_FRONT's stamps), the drive's name from /occvo/source."""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occvo_core.cameras import CAMERA_NAMES, CameraRig
from occvo_core.datasets.ros2_recording import Recording
from occvo_core.errors import DatasetError
from occvo_core.recording.messages import matrix, ns_of_header, stamp_of

IMAGE_TOPIC, INFO_TOPIC, TF_STATIC = "/{camera}/image_rect_compressed", "/{camera}/camera_info", "/tf_static"
GROUNDTRUTH_TOPIC, SOURCE_TOPIC = "/occvo/groundtruth", "/occvo/source"


@dataclass(frozen=True)
class RecordedKeyframe:
    token: str
    stamp: float
    files: list  # the six JPEGs as file objects


class RecordedCameras:
    def __init__(
        self,
        path: str | Path,
        image_topic: str = IMAGE_TOPIC,
        info_topic: str = INFO_TOPIC,
        ego_frame: str = "base_link",
        cameras: tuple[str, ...] = CAMERA_NAMES,
    ):
        self.path, self.cameras = Path(path), cameras
        self.image_topics = [image_topic.format(camera=c) for c in cameras]
        self.info_topics = [info_topic.format(camera=c) for c in cameras]
        required = {t: "--image-topic" for t in self.image_topics} | {
            t: "--camera-info-topic" for t in self.info_topics
        }
        required[TF_STATIC] = "/tf_static"
        topics = [*self.image_topics, *self.info_topics, TF_STATIC, GROUNDTRUTH_TOPIC, SOURCE_TOPIC]
        rec = Recording(path, topics, required)
        for t in self.image_topics:
            rec.expect(t, "sensor_msgs/msg/CompressedImage")
        for t in self.info_topics:
            rec.expect(t, "sensor_msgs/msg/CameraInfo")
        rec.expect(TF_STATIC, "tf2_msgs/msg/TFMessage")
        rec.expect(GROUNDTRUTH_TOPIC, "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")
        rec.expect(SOURCE_TOPIC, "std_msgs/msg/String")
        self.recording = rec
        counts = {t: len(rec.messages[t]) for t in self.image_topics + self.info_topics}
        if len(set(counts.values())) != 1:
            raise DatasetError(self.path, f"the cameras' topics hold different numbers of messages: {counts}")
        self._len = next(iter(counts.values()))
        statics = {}
        for msg in rec.decoded(TF_STATIC):
            for t in msg.transforms:
                if t.header.frame_id == ego_frame:
                    statics[t.child_frame_id] = matrix(t.transform.translation, t.transform.rotation)
        infos = [rec.decode(t, 0) for t in self.info_topics] if self._len else []
        missing = [i.header.frame_id for i in infos if i.header.frame_id not in statics]
        if missing:
            raise DatasetError(self.path, f"/tf_static has no {ego_frame} -> {missing}")
        self.cam_to_ego = np.array([statics[i.header.frame_id] for i in infos]).reshape(-1, 4, 4)
        info = rec.decoded(SOURCE_TOPIC)
        info = json.loads(info[-1].data) if info else {}
        self.name = str(info.get("drive", info.get("name", self.path.stem)))
        self.rate_hz = float(info.get("rate_hz", 2.0))
        truth = rec.decoded(GROUNDTRUTH_TOPIC)
        if len(truth) == self._len and self._len:
            poses = [m.pose.pose if hasattr(m, "child_frame_id") else m.pose for m in truth]
            self.gt_poses = np.array([matrix(p.position, p.orientation) for p in poses])
            self.stamps = np.array([stamp_of(ns_of_header(m.header)) for m in truth])
        else:
            self.gt_poses = None
            front = self.image_topics[0]
            self.stamps = np.array([stamp_of(ns_of_header(rec.decode(front, i).header)) for i in range(self._len)])

    def __len__(self) -> int:
        return self._len

    def __getitem__(self, index: int) -> RecordedKeyframe:
        if not 0 <= index < self._len:
            raise IndexError(index)
        files = [io.BytesIO(b) for b in self.jpegs(index)]
        return RecordedKeyframe(f"{self.path.name}:{index}", float(self.stamps[index]), files)

    def jpegs(self, index: int) -> list[bytes]:
        """The six compressed images of keyframe `index` as recorded."""
        return [bytes(np.asarray(self.recording.decode(t, index).data, np.uint8)) for t in self.image_topics]

    def camera_stamps(self, index: int) -> np.ndarray:
        return np.array([stamp_of(ns_of_header(self.recording.decode(t, index).header)) for t in self.image_topics])

    def intrinsics(self, index: int) -> tuple[np.ndarray, tuple[int, int]]:
        """(6,3,3) and the images' (width, height)."""
        infos = [self.recording.decode(t, index) for t in self.info_topics]
        return np.array([np.asarray(i.k, np.float64).reshape(3, 3) for i in infos]), (infos[0].width, infos[0].height)

    def rig(self, index: int) -> CameraRig:
        k, size = self.intrinsics(index)
        return CameraRig(k, self.cam_to_ego, size)
