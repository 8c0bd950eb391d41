"""The OCC-VO release format: occupancy/<scene>/<i>.npy (float (N,4) x,y,z,label) and trajectory/<scene>.kitti."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occvo_core.errors import DatasetError, InvalidFrameError
from occvo_core.frame import OccupancyFrame
from occvo_core.trajectory import read_stamped_trajectory


class OccVOReleaseScene:
    """A folder of <i>.npy frames; ground truth from `gt` or, when absent, ../../trajectory/<scene>.kitti if present.
    The release has no stamps: a TUM `gt` gives them, else they are index / rate_hz."""

    def __init__(self, scene_dir: str | Path, gt: str | Path | None = None, rate_hz: float = 2.0):
        self.root = Path(scene_dir)
        if not self.root.is_dir():
            raise DatasetError(self.root, "scene folder does not exist")
        numbered = [p for p in self.root.glob("*.npy") if p.stem.isdigit()]
        if not numbered:
            raise DatasetError(self.root, "no <i>.npy occupancy frames in the folder")
        self.files = sorted(numbered, key=lambda p: int(p.stem))  # numeric, not text order
        self.name = self.root.name
        self.rate_hz = rate_hz
        if gt is None:
            guess = self.root.parent.parent / "trajectory" / f"{self.name}.kitti"
            gt = guess if guess.is_file() else None
        self.stamps, self._gt = read_stamped_trajectory(gt) if gt is not None else (None, None)
        if self.stamps is not None and len(self.stamps) < len(self.files):
            self.stamps = None
        if self._gt is not None and len(self._gt) < len(self.files):
            raise DatasetError(gt, f"{len(self._gt)} poses for {len(self.files)} frames")

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> OccupancyFrame:
        if not 0 <= index < len(self.files):
            raise IndexError(index)
        path = self.files[index]
        try:
            array = np.load(path, allow_pickle=False)
        except EOFError:
            raise InvalidFrameError(
                f"{index} ({path})", "unreadable occupancy frame: empty or truncated file"
            ) from None
        except (OSError, ValueError) as exc:  # a text or pickle file named .npy: numpy's ValueError speaks of pickles
            why = "not a .npy array" if "pickle" in str(exc) else str(exc)
            raise InvalidFrameError(f"{index} ({path})", f"unreadable occupancy frame: {why}") from None
        stamp = float(self.stamps[index]) if self.stamps is not None else index / self.rate_hz
        frame = OccupancyFrame.from_array(array, index=index, stamp=stamp)
        frame.meta["path"] = str(path)
        try:
            return frame.validate()
        except InvalidFrameError as exc:
            raise InvalidFrameError(f"{index} ({path})", exc.reason) from None

    @property
    def gt_poses(self) -> np.ndarray | None:
        return None if self._gt is None else self._gt[: len(self.files)]


def write_release_scene(root: str | Path, name: str, frames, poses: np.ndarray | None = None) -> Path:
    """Write frames (iterable of OccupancyFrame) and poses in the release layout under root; return the scene folder."""
    scene_dir = Path(root) / "occupancy" / name
    scene_dir.mkdir(parents=True, exist_ok=True)
    for i, frame in enumerate(frames):
        np.save(scene_dir / f"{i}.npy", np.column_stack([frame.points, frame.labels.astype(np.float64)]))
    if poses is not None:
        from occvo_core.trajectory import write_kitti

        (Path(root) / "trajectory").mkdir(parents=True, exist_ok=True)
        write_kitti(Path(root) / "trajectory" / f"{name}.kitti", poses)
    return scene_dir
