"""nuScenes' devkit tables read as JSON, without the devkit: the full dataset or an extract that lacks tables the
odometry does not need (log, map, attribute, visibility, lidarseg) and the sweeps between keyframes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.errors import DatasetError

REQUIRED = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
OPTIONAL = ("sample_annotation", "instance", "category")  # the boxes: absent, a drive has none


def pose_matrix(record: dict) -> np.ndarray:
    """4x4 from a nuScenes translation and rotation (w, x, y, z)."""
    w, x, y, z = record["rotation"]
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    out[:3, 3] = record["translation"]
    return out


def is_nuscenes_root(path: Path) -> bool:
    """A folder in nuScenes' layout: a folder of tables (v1.0-*/scene.json) beside samples/."""
    return (path / "samples").is_dir() and any(path.glob("*/scene.json"))


def find_version(root: Path, version: str | None) -> Path:
    """The tables' folder: `version` when given, else the one folder under root that holds scene.json."""
    if version is not None:
        folder = root / version
        if not (folder / "scene.json").is_file():
            raise DatasetError(folder, f"no nuScenes tables of version {version!r} here (no scene.json)")
        return folder
    found = sorted(p.parent for p in root.glob("*/scene.json"))
    if len(found) != 1:
        what = "none" if not found else ", ".join(p.name for p in found)
        raise DatasetError(root, f"a nuScenes root holds one folder of tables (v1.0-mini, ...): found {what}")
    return found[0]


class NuScenesTables:
    """The tables of one version folder, each a dict token -> record."""

    def __init__(self, folder: Path):
        self.folder = folder
        missing = [t for t in REQUIRED if not (folder / f"{t}.json").is_file()]
        if missing:
            raise DatasetError(folder, f"nuScenes tables missing: {', '.join(m + '.json' for m in missing)}")
        self.rows = {t: self._load(t) for t in REQUIRED + OPTIONAL if (folder / f"{t}.json").is_file()}
        self.channel = {s["token"]: s["channel"] for s in self.rows["sensor"].values()}
        self.annotations_of: dict[str, list[dict]] = {}
        for a in self.rows.get("sample_annotation", {}).values():
            self.annotations_of.setdefault(a["sample_token"], []).append(a)
        self._keyframes_of: dict[str, list[dict]] = {}
        for sd in self.rows["sample_data"].values():
            if sd["is_key_frame"]:
                self._keyframes_of.setdefault(sd["sample_token"], []).append(sd)

    def _load(self, table: str) -> dict[str, dict]:
        path = self.folder / f"{table}.json"
        try:
            records = json.loads(path.read_text())
            return {r["token"]: r for r in records}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DatasetError(path, f"unreadable nuScenes table: {exc}") from None

    def get(self, table: str, token: str) -> dict:
        try:
            return self.rows[table][token]
        except KeyError:
            raise DatasetError(self.folder / f"{table}.json", f"no record {token!r}") from None

    def keyframes(self, sample: dict) -> dict[str, dict]:
        """channel -> the keyframe sample_data of a sample (the devkit's sample['data'])."""
        return {
            self.channel[self.get("calibrated_sensor", sd["calibrated_sensor_token"])["sensor_token"]]: sd
            for sd in self._keyframes_of.get(sample["token"], [])
        }
