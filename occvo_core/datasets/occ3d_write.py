"""Labels written in Occ3D-nuScenes' released layout, which open_scene reads back (occ3d_nuscenes):
<root>/gts/<scene>/<sample_token>/labels.npz and <root>/annotations.json with scene_infos[scene][token] =
{timestamp, ego_pose, prev, next, gt_path, camera_sensor}; other scenes and keys already in annotations.json are
kept."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from occvo_core.cameras import CAMERA_NAMES
from occvo_core.datasets.nuscenes_drive import LIDAR, NuScenesDrive
from occvo_core.datasets.occ3d_nuscenes import ANNOTATIONS, END, read_annotations
from occvo_core.io import write_text_atomic


def label_path(root: Path, scene: str, token: str) -> Path:
    return root / "gts" / scene / token / "labels.npz"


def write_labels(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """labels.npz, written whole or not at all."""
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(buffer.getvalue())
    tmp.replace(path)


def _pose(record: dict) -> dict:
    return {"translation": list(record["translation"]), "rotation": list(record["rotation"])}


def sample_info(drive: NuScenesDrive, index: int, prev: str, next_: str) -> dict:
    """Occ3D's per-sample record: the sample's stamp (us), the ego pose at the LiDAR sweep, each camera's image,
    intrinsics, extrinsics and ego pose at its own stamp."""
    k = drive[index]
    tables = drive.tables
    sample = tables.get("sample", k.token)
    data = tables.keyframes(sample)
    lidar = data.get(LIDAR) or data[CAMERA_NAMES[0]]
    cameras = {}
    for cam in CAMERA_NAMES:
        sd = data[cam]
        cs = tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
        cameras[cam] = {
            "img_path": sd["filename"],
            "intrinsics": cs["camera_intrinsic"],
            "extrinsic": _pose(cs),
            "ego_pose": _pose(tables.get("ego_pose", sd["ego_pose_token"])),
        }
    return {
        "timestamp": int(sample["timestamp"]),
        "ego_pose": _pose(tables.get("ego_pose", lidar["ego_pose_token"])),
        "prev": prev,
        "next": next_,
        "gt_path": f"gts/{drive.name}/{k.token}/labels.npz",
        "camera_sensor": cameras,
    }


def write_annotations(root: Path, drive: NuScenesDrive, indices: list[int]) -> Path:
    """annotations.json for the keyframes `indices` (in time order) of the drive's scene, chained prev/next."""
    path = root / ANNOTATIONS
    infos = read_annotations(root) if path.is_file() else {}
    # Occ3D's other keys (train_split, val_split) stay as they were
    whole = json.loads(path.read_text()) if path.is_file() else {}
    tokens = [drive[i].token for i in indices]
    infos[drive.name] = {
        t: sample_info(drive, i, tokens[n - 1] if n else END, tokens[n + 1] if n + 1 < len(tokens) else END)
        for n, (i, t) in enumerate(zip(indices, tokens))
    }
    write_text_atomic(path, json.dumps({**whole, "scene_infos": infos}, indent=1))
    return path
