"""nuScenes keyframes as camera-frame messages: the six JPEGs as recorded (not re-encoded), with their calibration
and timestamps, for the inference worker's model source (`occvo replay --nuscenes`)."""

from __future__ import annotations

from PIL import Image

from occvo_core.cameras import CAMERA_NAMES
from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.errors import DatasetError
from occvo_schemas.models import CameraFrame, CameraImage


class NuScenesCameraFrames:
    """A scene's samples as CameraFrame messages, stamped with the sample's timestamp (seconds)."""

    def __init__(self, dataroot, version: str | None = None, scene: str | None = None):
        self.scene = NuScenesDrive(dataroot, scene=scene, version=version)
        self.name, self.rate_hz = self.scene.name, self.scene.rate_hz

    def __len__(self) -> int:
        return len(self.scene)

    def __getitem__(self, index: int) -> CameraFrame:
        s = self.scene[index]
        images = []
        for name, path, k, t, stamp in zip(CAMERA_NAMES, s.files, s.intrinsics, s.cam_to_ego, s.camera_stamps):
            try:
                data = path.read_bytes()
                with Image.open(path) as im:
                    width, height, fmt = im.width, im.height, im.format
            except OSError as exc:
                raise DatasetError(path, f"unreadable camera image: {exc}") from None
            if fmt not in ("JPEG", "PNG"):
                raise DatasetError(path, f"camera images are JPEG or PNG, this is {fmt}")
            images.append(
                CameraImage(
                    camera=name,
                    encoding=fmt.lower(),
                    width=width,
                    height=height,
                    data=data,
                    intrinsics=k.tolist(),
                    extrinsics=t.tolist(),
                    stamp=float(stamp),
                )
            )
        return CameraFrame(stream="default", seq=index, stamp=s.stamp, images=images)

    @property
    def gt_poses(self):
        return self.scene.gt_poses
