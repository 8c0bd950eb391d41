"""The Occ3D-nuScenes layout: <scene>/<frame>/labels.npz with semantics (200,200,16) uint8 (17 = free),
mask_camera and mask_lidar (200,200,16) bool/uint8; poses from a KITTI or TUM file (a TUM file's stamps are the
frames' stamps). The released tree with annotations.json is read by occ3d_nuscenes, which builds this class."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from occvo_core.errors import DatasetError, InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import NUM_CLASSES, OCC3D_GRID, grid_to_points
from occvo_core.trajectory import read_stamped_trajectory

POSE_FILES = ("poses.kitti", "poses.txt", "poses.tum")


class Occ3DScene:
    """Frames are the sub-folders holding labels.npz, in numeric order when all names are numbers, else in the
    order given by `frames` (Occ3D's own folders are sample tokens, whose time order annotations.json tells), or the
    label `files` given. A frame is the occupied voxels inside `mask` ("camera", the default, "lidar" or "none").
    `poses` is a trajectory file or an (N,4,4) array; stamps are `stamps`, a TUM file's, or index / rate_hz."""

    def __init__(
        self,
        scene_dir: str | Path,
        poses: str | Path | np.ndarray | None = None,
        mask: Literal["none", "camera", "lidar"] = "camera",
        rate_hz: float = 2.0,
        frames: list[str] | None = None,
        files: list[Path] | None = None,
        stamps: np.ndarray | None = None,
        name: str | None = None,
    ):
        self.root = Path(scene_dir)
        if not self.root.is_dir():
            raise DatasetError(self.root, "scene folder does not exist")
        if mask not in ("none", "camera", "lidar"):
            raise DatasetError(self.root, f"mask must be 'none', 'camera' or 'lidar', got {mask!r}")
        self.mask = mask
        self.name = name or self.root.name
        self.rate_hz = rate_hz
        self.stamps = None if stamps is None else np.asarray(stamps, np.float64)
        self.files = [Path(f) for f in files] if files is not None else self._frame_files(frames)
        if poses is None:
            poses = next((self.root / n for n in POSE_FILES if (self.root / n).is_file()), None)
        self._gt = None
        if isinstance(poses, np.ndarray):
            self._gt = np.asarray(poses, np.float64)
        elif poses is not None:
            file_stamps, self._gt = read_stamped_trajectory(poses)
            if self.stamps is None and file_stamps is not None and len(file_stamps) >= len(self.files):
                self.stamps = file_stamps[: len(self.files)]
        if self._gt is not None and len(self._gt) < len(self.files):
            raise DatasetError(
                poses if not isinstance(poses, np.ndarray) else self.root,
                f"{len(self._gt)} poses for {len(self.files)} frames",
            )
        if self.stamps is not None and len(self.stamps) != len(self.files):
            raise DatasetError(self.root, f"{len(self.stamps)} stamps for {len(self.files)} frames")

    def _frame_files(self, frames: list[str] | None) -> list[Path]:
        found = {p.parent.name: p for p in self.root.glob("*/labels.npz")}
        if not found:
            raise DatasetError(self.root, "no <frame>/labels.npz files in the folder")
        if frames is not None:
            missing = [f for f in frames if f not in found]
            if missing:
                raise DatasetError(self.root, f"frames without labels.npz: {missing[:5]}")
            return [found[n] for n in frames]
        if all(n.isdigit() for n in found):
            return [found[n] for n in sorted(found, key=int)]
        raise DatasetError(
            self.root,
            "frame folders are not all numbers (sample tokens?): open the release root, "
            "whose annotations.json orders them, or give their order with frames=[...]",
        )

    def __len__(self) -> int:
        return len(self.files)

    def load(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(semantics uint8, mask_camera bool, mask_lidar bool) of a frame, checked."""
        if not 0 <= index < len(self.files):
            raise IndexError(index)
        path = self.files[index]
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: np.asarray(z[k]) for k in ("semantics", "mask_camera", "mask_lidar") if k in z.files}
        except (OSError, ValueError, EOFError) as exc:
            raise DatasetError(path, f"unreadable labels.npz: {exc}") from None
        if "semantics" not in arrays:
            raise DatasetError(path, "labels.npz has no 'semantics' array")
        shape = OCC3D_GRID.shape
        sem = arrays["semantics"]
        if sem.shape != shape:
            raise DatasetError(path, f"semantics has shape {sem.shape}, expected {shape}")
        if not np.issubdtype(sem.dtype, np.integer) or sem.min() < 0 or sem.max() >= NUM_CLASSES:
            raise DatasetError(path, f"semantics must be integers 0..{NUM_CLASSES - 1} (17 = free)")
        masks = []
        for key in ("mask_camera", "mask_lidar"):
            if key not in arrays:
                if self.mask == key.split("_")[1]:
                    raise DatasetError(path, f"labels.npz has no '{key}' array (mask={self.mask!r})")
                masks.append(np.ones(shape, bool))
                continue
            m = arrays[key]
            if m.shape != shape:
                raise DatasetError(path, f"{key} has shape {m.shape}, expected {shape}")
            masks.append(m.astype(bool))
        return sem.astype(np.uint8), masks[0], masks[1]

    def __getitem__(self, index: int) -> OccupancyFrame:
        try:
            sem, cam, lidar = self.load(index)
        except DatasetError as exc:  # one unreadable frame is a bad frame (--skip-bad-frames), not a bad scene
            raise InvalidFrameError(f"{index} ({self.files[index]})", exc.reason) from None
        mask = {"none": None, "camera": cam, "lidar": lidar}[self.mask]
        points, labels = grid_to_points(sem, OCC3D_GRID, mask)
        stamp = float(self.stamps[index]) if self.stamps is not None else index / self.rate_hz
        frame = OccupancyFrame(points, labels, index, stamp, {"path": str(self.files[index]), "mask": self.mask})
        try:
            return frame.validate()
        except InvalidFrameError as exc:
            raise InvalidFrameError(f"{index} ({self.files[index]})", exc.reason) from None

    @property
    def gt_poses(self) -> np.ndarray | None:
        return None if self._gt is None else self._gt[: len(self.files)]
