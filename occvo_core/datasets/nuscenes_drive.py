"""A nuScenes drive in the devkit's folder layout (the full dataset or an extract): per keyframe the six camera
images with intrinsics, camera -> ego extrinsics and stamps, the roof LiDAR sweep, the 3D boxes with their Occ3D
class, and the ego pose at the LiDAR sweep (Occ3D's; ground truth, for evaluation and labels only).

    drive = NuScenesDrive("../shared/data/nuscenes-mini", scene="scene-0916")
    k = drive[0]                 # Keyframe: cameras, lidar file and calibration, ego pose, stamps
    points = drive.lidar_in_ego(0)   # (N, 3) float64, the sweep in the ego frame at its stamp
    boxes = drive.boxes(0)       # Boxes in the world frame
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occvo_core.cameras import CAMERA_NAMES, CameraRig
from occvo_core.datasets.nuscenes_classes import occ3d_class
from occvo_core.datasets.nuscenes_tables import NuScenesTables, find_version, pose_matrix
from occvo_core.errors import DatasetError

LIDAR = "LIDAR_TOP"


@dataclass(frozen=True)
class Keyframe:
    """One sample: camera order CAMERA_NAMES; stamps in seconds; poses ego -> world, extrinsics sensor -> ego."""

    token: str
    stamp: float
    files: list[Path]
    intrinsics: np.ndarray  # (6, 3, 3) for the files' full size
    cam_to_ego: np.ndarray  # (6, 4, 4)
    camera_stamps: np.ndarray  # (6,) each image's own capture time
    camera_ego_poses: np.ndarray  # (6, 4, 4) the ego pose at each image's stamp
    lidar_file: Path | None  # None: a camera-only drive
    lidar_to_ego: np.ndarray | None  # (4, 4)
    lidar_stamp: float | None
    ego_pose: np.ndarray  # (4, 4) at the LiDAR sweep's stamp (CAM_FRONT's without a LiDAR)


@dataclass(frozen=True)
class Boxes:
    """A keyframe's annotated boxes in the world frame; sizes as nuScenes gives them (width, length, height)."""

    centres: np.ndarray  # (M, 3)
    rotations: np.ndarray  # (M, 3, 3) box -> world (box x along its length)
    sizes: np.ndarray  # (M, 3) w, l, h
    labels: np.ndarray  # (M,) Occ3D class
    instances: list[str]
    categories: list[str]

    def __len__(self) -> int:
        return len(self.labels)


class NuScenesDrive:
    def __init__(self, dataroot: str | Path, scene: str | None = None, version: str | None = None):
        self.root = Path(dataroot)
        if not self.root.is_dir():
            raise DatasetError(self.root, "no such nuScenes folder")
        self.tables = NuScenesTables(find_version(self.root, version))
        scenes = {s["name"]: s for s in self.tables.rows["scene"].values()}
        if scene is None and len(scenes) == 1:
            scene = next(iter(scenes))
        if scene not in scenes:
            names = sorted(scenes)
            raise DatasetError(self.tables.folder, f"no scene {scene!r}: name one of {names[:8]} (--scene)")
        self.name, self.rate_hz = scene, 2.0
        self.samples: list[Keyframe] = []
        token = scenes[scene]["first_sample_token"]
        while token:
            sample = self.tables.get("sample", token)
            self.samples.append(self._keyframe(sample))
            token = sample["next"]
        self.categories = self._categories()

    def _sensor(self, sd: dict) -> tuple[np.ndarray, np.ndarray, dict]:
        cs = self.tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
        return pose_matrix(cs), pose_matrix(self.tables.get("ego_pose", sd["ego_pose_token"])), cs

    def _keyframe(self, sample: dict) -> Keyframe:
        data = self.tables.keyframes(sample)
        missing = [c for c in CAMERA_NAMES if c not in data]
        if missing:
            raise DatasetError(self.tables.folder, f"sample {sample['token']} has no keyframe of {missing}")
        files, ks, exts, stamps, egos = [], [], [], [], []
        for cam in CAMERA_NAMES:
            ext, ego, cs = self._sensor(data[cam])
            files.append(self.root / data[cam]["filename"])
            ks.append(np.asarray(cs["camera_intrinsic"], np.float64).reshape(3, 3))
            exts.append(ext)
            stamps.append(data[cam]["timestamp"] / 1e6)
            egos.append(ego)
        lidar, (lidar_file, lidar_to_ego, lidar_stamp, ego) = data.get(LIDAR), (None, None, None, egos[0])
        if lidar is not None:
            lidar_file, lidar_stamp = self.root / lidar["filename"], lidar["timestamp"] / 1e6
            lidar_to_ego, ego, _ = self._sensor(lidar)
        return Keyframe(
            sample["token"], sample["timestamp"] / 1e6, files, np.array(ks), np.array(exts), np.array(stamps),
            np.array(egos), lidar_file, lidar_to_ego, lidar_stamp, ego,
        )  # fmt: skip

    def _categories(self) -> dict[str, str]:
        """instance token -> category name."""
        rows = self.tables.rows
        names = {c["token"]: c["name"] for c in rows.get("category", {}).values()}
        return {i["token"]: names.get(i["category_token"], "") for i in rows.get("instance", {}).values()}

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> Keyframe:
        return self.samples[index]

    @property
    def gt_poses(self) -> np.ndarray:
        return np.array([s.ego_pose for s in self.samples])

    @property
    def stamps(self) -> np.ndarray:
        return np.array([s.stamp for s in self.samples])

    def lidar_sweep(self, index: int) -> np.ndarray:
        """The keyframe's sweep as recorded: (N, 5) float32 x, y, z (sensor frame), intensity, ring."""
        path = self.samples[index].lidar_file
        if path is None:
            raise DatasetError(self.tables.folder, f"sample {self.samples[index].token} has no {LIDAR} keyframe")
        try:
            raw = np.fromfile(path, dtype=np.float32)
        except OSError as exc:
            raise DatasetError(path, f"unreadable LiDAR sweep: {exc}") from None
        if raw.size == 0 or raw.size % 5:
            raise DatasetError(path, f"a LiDAR sweep is float32 (N, 5): {raw.size} values")
        return raw.reshape(-1, 5)

    def lidar_in_ego(self, index: int) -> np.ndarray:
        """The sweep's points (N, 3) in the ego frame at the sweep's stamp, float64."""
        xyz = self.lidar_sweep(index)[:, :3].astype(np.float64)
        t = self.samples[index].lidar_to_ego
        return xyz @ t[:3, :3].T + t[:3, 3]

    def boxes(self, index: int) -> Boxes:
        """The keyframe's annotated boxes (none where the drive has no annotation tables)."""
        rows = self.tables.annotations_of.get(self.samples[index].token, [])
        rows = sorted(rows, key=lambda a: a["instance_token"])  # one order, whatever the table's
        poses = np.array([pose_matrix(a) for a in rows]).reshape(-1, 4, 4)
        cats = [self.categories.get(a["instance_token"], "") for a in rows]
        return Boxes(
            poses[:, :3, 3], poses[:, :3, :3], np.array([a["size"] for a in rows], np.float64).reshape(-1, 3),
            np.array([occ3d_class(c) for c in cats], np.uint8), [a["instance_token"] for a in rows], cats,
        )  # fmt: skip

    def rig(self, index: int) -> CameraRig:
        """The keyframe's six cameras as occvo's camera model (full-size images)."""
        k = self.samples[index]
        width, height = _image_size(k.files[0])
        return CameraRig(k.intrinsics, k.cam_to_ego, (width, height))

    def ego_at_camera(self, index: int, camera: int) -> np.ndarray:
        """4x4 from the ego at the sweep's stamp to the ego at a camera's stamp, through the world: the car moves
        up to ~0.5 m between the LiDAR's and a camera's instant (the devkit's map_pointcloud_to_image chain)."""
        k = self.samples[index]
        return np.linalg.inv(k.camera_ego_poses[camera]) @ k.ego_pose


class DriveSource:
    """What a scene source made from a drive's keyframes shares: one frame a keyframe, the drive's ground truth and
    rate, a name saying how its occupancy is made."""

    def __init__(self, drive: NuScenesDrive, made_by: str):
        self.drive = drive
        self.name, self.rate_hz = f"{drive.name}-{made_by}", drive.rate_hz

    def __len__(self) -> int:
        return len(self.drive)

    @property
    def gt_poses(self) -> np.ndarray:
        return self.drive.gt_poses


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.width, im.height
    except OSError as exc:
        raise DatasetError(path, f"unreadable camera image: {exc}") from None
