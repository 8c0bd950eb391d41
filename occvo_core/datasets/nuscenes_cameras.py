"""nuScenes camera keyframes through nuscenes-devkit: for each sample of a scene, the six camera images with their
calibration (intrinsics; sensor -> ego extrinsics) and timestamps, and the ego poses as ground truth.

The devkit pins numpy < 2, which this project has outgrown: install it with `pip install --no-deps nuscenes-devkit`
beside `pip install 'occvo[nuscenes]'` (what its import needs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.cameras import CAMERA_NAMES
from occvo_core.errors import ConfigError, DatasetError

EGO_CHANNEL = "LIDAR_TOP"  # the sample's ego pose is the one at its lidar sweep (as Occ3D's), else CAM_FRONT's


def _matrix(record: dict) -> np.ndarray:
    """4x4 from a nuScenes translation and rotation (w, x, y, z)."""
    w, x, y, z = record["rotation"]
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    out[:3, 3] = record["translation"]
    return out


@dataclass
class SampleCameras:
    """One keyframe: camera order CAMERA_NAMES; stamps in seconds."""

    token: str
    stamp: float
    files: list[Path]
    intrinsics: np.ndarray  # (6, 3, 3) for the files' full size
    cam_to_ego: np.ndarray  # (6, 4, 4)
    camera_stamps: np.ndarray  # (6,) each image's own capture time
    ego_pose: np.ndarray  # (4, 4) ego -> world


class NuScenesCameraScene:
    def __init__(self, dataroot: str | Path, version: str = "v1.0-mini", scene: str = "scene-0061"):
        try:
            from nuscenes.nuscenes import NuScenes
        except ModuleNotFoundError as exc:
            raise ConfigError(
                f"nuScenes input needs nuscenes-devkit ({exc}): pip install --no-deps nuscenes-devkit "
                "and pip install 'occvo[nuscenes]'"
            ) from None
        self.root = Path(dataroot)
        if not (self.root / version).is_dir():
            raise DatasetError(self.root / version, f"no nuScenes tables of version {version!r} here")
        try:
            self.nusc = NuScenes(version=version, dataroot=str(self.root), verbose=False)
        except (AssertionError, KeyError, ValueError, OSError) as exc:
            raise DatasetError(self.root / version, f"nuscenes-devkit cannot load the tables: {exc!r}") from None
        found = [s for s in self.nusc.scene if s["name"] == scene]
        if not found:
            names = sorted(s["name"] for s in self.nusc.scene)
            raise DatasetError(self.root / version, f"no scene {scene!r} ({len(names)} scenes, e.g. {names[:3]})")
        self.name, self.rate_hz = scene, 2.0
        self.tokens, token = [], found[0]["first_sample_token"]
        while token:
            self.tokens.append(token)
            token = self.nusc.get("sample", token)["next"]
        self.samples = [self._sample(t) for t in self.tokens]

    def _sample(self, token: str) -> SampleCameras:
        sample = self.nusc.get("sample", token)
        missing = [c for c in CAMERA_NAMES if c not in sample["data"]]
        if missing:
            raise DatasetError(self.root, f"sample {token} has no keyframe of {missing}")
        files, ks, ts, stamps = [], [], [], []
        for cam in CAMERA_NAMES:
            sd = self.nusc.get("sample_data", sample["data"][cam])
            cs = self.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            files.append(self.root / sd["filename"])
            ks.append(np.asarray(cs["camera_intrinsic"], np.float64).reshape(3, 3))
            ts.append(_matrix(cs))
            stamps.append(sd["timestamp"] / 1e6)
        ego_sd = self.nusc.get("sample_data", sample["data"].get(EGO_CHANNEL, sample["data"]["CAM_FRONT"]))
        ego = _matrix(self.nusc.get("ego_pose", ego_sd["ego_pose_token"]))
        return SampleCameras(token, sample["timestamp"] / 1e6, files, np.array(ks), np.array(ts), np.array(stamps), ego)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> SampleCameras:
        return self.samples[index]

    @property
    def gt_poses(self) -> np.ndarray:
        return np.array([s.ego_pose for s in self.samples])

    @property
    def stamps(self) -> np.ndarray:
        return np.array([s.stamp for s in self.samples])
