"""Scene sources, one file per format, behind one opener."""

from __future__ import annotations

from pathlib import Path

from occvo_core.datasets.base import SceneSource, iterate
from occvo_core.datasets.occvo_release import OccVOReleaseScene
from occvo_core.errors import DatasetError

__all__ = ["SceneSource", "iterate", "OccVOReleaseScene", "open_scene"]


def open_scene(path: str | Path, gt: str | Path | None = None) -> SceneSource:
    """An OCC-VO release folder (<i>.npy frames) or an Occ3D scene folder (<frame>/labels.npz), told apart by content."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, "no such scene folder")
    if not path.is_dir():
        raise DatasetError(path, "a scene is a folder of frames")
    if any(p.stem.isdigit() for p in path.glob("*.npy")):
        return OccVOReleaseScene(path, gt=gt)
    if any(path.glob("*/labels.npz")):
        from occvo_core.datasets.occ3d import Occ3DScene

        return Occ3DScene(path, poses=gt)
    raise DatasetError(path, "neither OCC-VO release frames (<i>.npy) nor Occ3D frames (<frame>/labels.npz)")
