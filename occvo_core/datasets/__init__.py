"""Scene sources, one file per format, behind one opener."""

from __future__ import annotations

from pathlib import Path

from occvo_core.datasets.base import SceneSource, iterate
from occvo_core.datasets.nuscenes_tables import is_nuscenes_root
from occvo_core.datasets.occvo_release import OccVOReleaseScene
from occvo_core.errors import ConfigError, DatasetError
from occvo_core.trajectory import read_trajectory

__all__ = ["SceneSource", "iterate", "OccVOReleaseScene", "open_scene"]


def open_scene(
    path: str | Path,
    gt: str | Path | None = None,
    scene: str | None = None,
    mask: str = "camera",
    occupancy: str | None = None,
) -> SceneSource:
    """An OCC-VO release folder (<i>.npy frames), an Occ3D-nuScenes root (annotations.json + gts/) with `scene`, one
    of its gts/<scene> folders, an Occ3D scene folder (<frame>/labels.npz), or a nuScenes drive (devkit layout) with
    `occupancy="lidar"`, told apart by content. `mask` is Occ3D's visibility mask ("camera", "lidar" or "none"); `gt`
    overrides the poses of the annotations."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, "no such scene folder")
    if not path.is_dir():
        raise DatasetError(path, "a scene is a folder of frames")
    if is_nuscenes_root(path):
        return _nuscenes_scene(path, scene, gt, occupancy)
    if occupancy is not None:
        raise ConfigError(f"--occupancy {occupancy} makes occupancy from a nuScenes drive's sensors; {path} is not one")
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


def _nuscenes_scene(path: Path, scene: str | None, gt, occupancy: str | None) -> SceneSource:
    if occupancy != "lidar":
        raise ConfigError(
            f"{path} is a nuScenes drive (cameras and LiDAR, no occupancy): say how to make its occupancy, "
            "--occupancy lidar (from its sweeps) or --from-images (the camera model)"
        )
    if gt is not None:
        raise ConfigError("a nuScenes drive brings its ground truth (the ego poses at its sweeps): no --gt")
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.lidar.source import LidarOccupancyScene

    return LidarOccupancyScene(NuScenesDrive(path, scene=scene))
