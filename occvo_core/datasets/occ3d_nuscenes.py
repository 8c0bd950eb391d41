"""Occ3D-nuScenes as released: <root>/gts/<scene>/<sample_token>/labels.npz with <root>/annotations.json.

annotations.json holds scene_infos[scene][token] = {timestamp (microseconds), ego_pose {translation, rotation as
w, x, y, z}, prev, next ("EOF" at the ends), gt_path, camera_sensor, ...}. The frames of a scene are its tokens
in the order of the prev/next chain; ground truth is the ego poses, stamps the timestamps in seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.datasets.occ3d import Occ3DScene
from occvo_core.errors import DatasetError

ANNOTATIONS = "annotations.json"
END = "EOF"


def release_root(path: str | Path) -> Path | None:
    """The release root a folder belongs to: the folder itself, or the root of a gts/<scene> folder; None if neither."""
    path = Path(path)
    if (path / ANNOTATIONS).is_file():
        return path
    if path.parent.name == "gts" and (path.parent.parent / ANNOTATIONS).is_file():
        return path.parent.parent
    return None


def read_annotations(root: str | Path) -> dict:
    """scene_infos of a release root, checked for shape."""
    path = Path(root) / ANNOTATIONS
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(path, f"unreadable annotations: {exc}") from None
    infos = data.get("scene_infos") if isinstance(data, dict) else None
    if not isinstance(infos, dict) or not all(isinstance(v, dict) for v in infos.values()):
        raise DatasetError(path, "no 'scene_infos' object of scene -> {sample_token: info}")
    return infos


def list_scenes(root: str | Path) -> list[dict]:
    """Each scene of a release root: name, number of samples, first and last timestamp (s)."""
    out = []
    for name, samples in sorted(read_annotations(root).items()):
        stamps = [s.get("timestamp") for s in samples.values() if isinstance(s, dict)]
        stamps = [t / 1e6 for t in stamps if isinstance(t, (int, float))]
        out.append(
            {
                "scene": name,
                "samples": len(samples),
                "start": min(stamps, default=None),
                "end": max(stamps, default=None),
            }
        )
    return out


def chain_order(samples: dict, where: object) -> list[str]:
    """Sample tokens in time order, following next from the one whose prev is "EOF"."""
    heads = [t for t, s in samples.items() if s.get("prev") == END]
    if len(heads) != 1:
        raise DatasetError(
            where, f'a scene\'s prev/next chain needs one first sample (prev = "EOF"), found {len(heads)}'
        )
    order, token, seen = [], heads[0], set()
    while token != END:
        if token in seen:
            raise DatasetError(where, f"prev/next chain loops at sample {token}")
        if token not in samples:
            raise DatasetError(where, f"prev/next chain names sample {token}, which the scene does not hold")
        seen.add(token)
        order.append(token)
        token = samples[token].get("next", END)
    if len(order) != len(samples):
        lost = sorted(set(samples) - seen)[:3]
        raise DatasetError(where, f"prev/next chain reaches {len(order)} of {len(samples)} samples (not: {lost})")
    return order


def ego_pose_matrix(ego_pose: dict, where: object) -> np.ndarray:
    """4x4 ego-to-world from nuScenes' translation (x, y, z) and rotation (w, x, y, z)."""
    try:
        t = np.asarray(ego_pose["translation"], np.float64).reshape(3)
        w, x, y, z = np.asarray(ego_pose["rotation"], np.float64).reshape(4)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(where, "ego_pose needs translation [x, y, z] and rotation [w, x, y, z]") from None
    if not (np.all(np.isfinite(t)) and np.isfinite([w, x, y, z]).all()) or np.linalg.norm([w, x, y, z]) < 1e-9:
        raise DatasetError(where, "ego_pose has a non-finite translation or a zero rotation")
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    pose[:3, 3] = t
    return pose


def _label_file(root: Path, scene: str, token: str, info: dict) -> Path:
    """gts/<scene>/<token>/labels.npz; gt_path, written relative to the authors' checkout, is used from 'gts/' on."""
    parts = Path(str(info.get("gt_path", ""))).parts
    if "gts" in parts:
        candidate = root.joinpath(*parts[parts.index("gts") :])
        if candidate.is_file():
            return candidate
    return root / "gts" / scene / token / "labels.npz"


def open_release_scene(root: str | Path, scene: str, mask: str = "camera") -> Occ3DScene:
    """One scene of a release root as an Occ3DScene with the chain's order, ego poses and timestamps."""
    root = Path(root)
    infos = read_annotations(root)
    if scene not in infos:
        names = sorted(infos)
        raise DatasetError(root / ANNOTATIONS, f"no scene {scene!r} ({len(names)} scenes, e.g. {names[:3]})")
    samples = infos[scene]
    where = f"{root / ANNOTATIONS} [{scene}]"
    if not samples or not all(isinstance(s, dict) for s in samples.values()):
        raise DatasetError(where, "a scene is an object of sample_token -> info")
    order = chain_order(samples, where)
    stamps = []
    for token in order:
        t = samples[token].get("timestamp")
        if not isinstance(t, (int, float)) or isinstance(t, bool) or not np.isfinite(t):
            raise DatasetError(where, f"sample {token} has no numeric timestamp (microseconds)")
        stamps.append(t / 1e6)
    if np.any(np.diff(stamps) <= 0):
        raise DatasetError(where, "timestamps do not increase along the prev/next chain")
    poses = np.array([ego_pose_matrix(samples[t].get("ego_pose") or {}, f"{where} sample {t}") for t in order])
    files = [_label_file(root, scene, t, samples[t]) for t in order]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise DatasetError(root / "gts" / scene, f"{len(missing)} samples without labels.npz, e.g. {missing[0]}")
    return Occ3DScene(root / "gts" / scene, poses=poses, mask=mask, files=files, stamps=np.array(stamps), name=scene)
