"""Write a synthetic scene in the OCC-VO release format and in the Occ3D-nuScenes layout, with its ground truth.

Release: <root>/occupancy/<scene>/<i>.npy + <root>/trajectory/<scene>.kitti (the noisy frames, as served).
Occ3D:   <root>/<scene>/<i>/labels.npz (semantics: the noise-free occupancy, as Occ3D's ground truth, or the
         noisy prediction; mask_camera, mask_lidar: the visibility passes) + <root>/<scene>/poses.kitti.
Both also get <scene>.truth.npz beside them: static map (points, labels) and dynamic tracks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from occvo_core.datasets.occvo_release import write_release_scene
from occvo_core.grid import FREE, points_to_grid
from occvo_core.sim.scene import SyntheticScene
from occvo_core.trajectory import write_kitti


def write_truth(path: str | Path, scene: SyntheticScene) -> Path:
    """Static map and dynamic tracks of a scene as one npz (arrays only, no pickles)."""
    points, labels = scene.static_map()
    tracks = scene.dynamic_tracks()
    np.savez_compressed(
        path,
        static_points=points,
        static_labels=labels,
        gt_poses=scene.gt_poses,
        track_ids=np.array([t.id for t in tracks], np.int64),
        track_labels=np.array([t.label for t in tracks], np.uint8),
        track_sizes=np.array([t.size for t in tracks], np.float64).reshape(-1, 3),
        track_poses=np.array([t.poses for t in tracks], np.float64).reshape(-1, len(scene), 4, 4),
    )
    return Path(path)


def export_release(scene: SyntheticScene, root: str | Path) -> Path:
    """The scene in the OCC-VO release layout; returns the scene folder (readable by OccVOReleaseScene)."""
    root = Path(root)
    scene_dir = write_release_scene(root, scene.name, (scene[i] for i in range(len(scene))), scene.gt_poses)
    write_truth(root / "trajectory" / f"{scene.name}.truth.npz", scene)
    return scene_dir


def export_occ3d(scene: SyntheticScene, root: str | Path, semantics: Literal["truth", "prediction"] = "truth") -> Path:
    """The scene in the Occ3D layout; returns the scene folder (readable by Occ3DScene).

    semantics="truth" writes what Occ3D's labels.npz holds: the noise-free occupancy of the whole grid, observed
    or not, with the visibility masks (read back with mask="camera" it gives the noise-free frames; it is also what
    an occupancy network trains on). "prediction" writes the noisy frames as served, free elsewhere."""
    if semantics not in ("truth", "prediction"):
        raise ValueError(f"semantics must be 'truth' or 'prediction', got {semantics!r}")
    scene_dir = Path(root) / scene.name
    for i in range(len(scene)):
        cam = scene.camera_mask(i)
        if semantics == "truth":
            grid = scene.true_grid(i)
        else:
            frame = scene[i]
            grid = points_to_grid(frame.points, frame.labels)
            cam |= grid != FREE  # jitter can move a thin voxel just outside the pass's mask
        out = scene_dir / str(i)
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            out / "labels.npz",
            semantics=grid,
            mask_camera=cam.astype(np.uint8),
            mask_lidar=scene.lidar_mask(i).astype(np.uint8),
        )
    write_kitti(scene_dir / "poses.kitti", scene.gt_poses)
    write_truth(scene_dir / "truth.npz", scene)
    return scene_dir
