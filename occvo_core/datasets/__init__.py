"""Scene sources, one file per format, behind one opener."""

from __future__ import annotations

from pathlib import Path

from occvo_core.datasets.base import SceneSource, iterate
from occvo_core.datasets.occvo_release import OccVOReleaseScene
from occvo_core.errors import DatasetError
from occvo_core.trajectory import read_trajectory

__all__ = ["SceneSource", "iterate", "OccVOReleaseScene", "open_scene"]


def open_scene(
    path: str | Path, gt: str | Path | None = None, scene: str | None = None, mask: str = "camera"
) -> SceneSource:
    """An OCC-VO release folder (<i>.npy frames), an Occ3D-nuScenes root (annotations.json + gts/) with `scene`, one
    of its gts/<scene> folders, or an Occ3D scene folder (<frame>/labels.npz), told apart by content. `mask` is
    Occ3D's visibility mask ("camera", "lidar" or "none"); `gt` overrides the poses of the annotations."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, "no such scene folder")
    if not path.is_dir():
        raise DatasetError(path, "a scene is a folder of frames")
    from occvo_core.datasets import occ3d_nuscenes

    root = occ3d_nuscenes.release_root(path)
    if root is not None:
        if root == path and scene is None:
            raise DatasetError(
                path, "an Occ3D-nuScenes root holds many scenes: name one (--scene; --list-scenes lists them)"
            )
        source = occ3d_nuscenes.open_release_scene(root, scene or path.name, mask=mask)
        if gt is not None:
            from occvo_core.datasets.occ3d import Occ3DScene

            source = Occ3DScene(
                source.root,
                poses=read_trajectory(gt),
                mask=mask,
                files=source.files,
                stamps=source.stamps,
                name=source.name,
            )
        return source
    if scene is not None:
        raise DatasetError(path, f"--scene {scene} needs an Occ3D-nuScenes root (a folder with annotations.json)")
    if any(p.stem.isdigit() for p in path.glob("*.npy")):
        return OccVOReleaseScene(path, gt=gt)
    if any(path.glob("*/labels.npz")):
        from occvo_core.datasets.occ3d import Occ3DScene

        return Occ3DScene(path, poses=gt, mask=mask)
    raise DatasetError(path, "neither OCC-VO release frames (<i>.npy) nor Occ3D frames (<frame>/labels.npz)")
