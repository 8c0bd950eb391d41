"""Six cameras from a ROS 2 recording (occvo_core/datasets/ros2_recording.py), as nuscenes2mcap records a drive:
per camera `sensor_msgs/CompressedImage` on /<CAMERA>/image_rect_compressed and `sensor_msgs/CameraInfo` on
/<CAMERA>/camera_info (topic templates with {camera}), the cameras' extrinsics on /tf_static (base_link -> the
camera's frame id). Keyframe i is the i-th image of every camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occvo_core.cameras import CAMERA_NAMES, CameraRig
from occvo_core.datasets.ros2_recording import Recording
from occvo_core.errors import DatasetError
from occvo_core.recording.messages import matrix, ns_of_header, stamp_of

IMAGE_TOPIC, INFO_TOPIC, TF_STATIC = "/{camera}/image_rect_compressed", "/{camera}/camera_info", "/tf_static"


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
        rec = Recording(path, [*self.image_topics, *self.info_topics, TF_STATIC], required)
        for t in self.image_topics:
            rec.expect(t, "sensor_msgs/msg/CompressedImage")
        for t in self.info_topics:
            rec.expect(t, "sensor_msgs/msg/CameraInfo")
        rec.expect(TF_STATIC, "tf2_msgs/msg/TFMessage")
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

    def __len__(self) -> int:
        return self._len

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
