"""The camera model on a real drive: its predictions from the six real images of each keyframe scored against
Occ3D-style labels (occvo make-occupancy's, or Occ3D's own) inside the labels' camera mask, as Occ3D scores."""

from __future__ import annotations

from pathlib import Path

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.errors import DatasetError
from occvo_core.models.image_source import NuScenesImageSource
from occvo_core.models.metrics import OccMetrics


def labels_by_token(labels_root: Path, scene: str):
    """The scene's labels (an Occ3D-nuScenes root) and sample token -> frame index in them."""
    from occvo_core.datasets.occ3d_nuscenes import open_release_scene, release_root

    root = release_root(labels_root)
    if root is None:
        raise DatasetError(labels_root, "no annotations.json: give the folder `occvo make-occupancy --out` wrote")
    labels = open_release_scene(root, scene)
    return labels, {f.parent.name: n for n, f in enumerate(labels.files)}


def evaluate_drive(source: NuScenesImageSource, labels_root: Path, keyframes: list[int], progress=None) -> OccMetrics:
    """Occ3D's metrics of `source`'s predicted grids (use a predictor without thresholds or mask: the argmax)
    over `keyframes`, inside each keyframe's mask_camera."""
    drive: NuScenesDrive = source.drive
    labels, index = labels_by_token(labels_root, drive.name)
    metrics = OccMetrics()
    for i in keyframes:
        token = drive[i].token
        if token not in index:
            raise DatasetError(labels.root, f"no labels for keyframe {i} (sample {token}): make them first")
        semantics, mask_camera, _ = labels.load(index[token])
        metrics.update(source.grid(i), semantics, mask_camera)
        if progress is not None:
            progress(i)
    return metrics
