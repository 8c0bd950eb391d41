"""A scene source whose occupancy comes from the network: each frame's six camera images are rendered from the
scene's true occupancy and passed through TPV-Former (images -> network -> odometry, on synthetic scenes).

    scene = SyntheticScene(seed=0, frames=40)
    source = ImageOccupancySource(scene, OccupancyPredictor("checkpoint.pt"))
    frame = source[0]   # OccupancyFrame of the predicted occupied voxels, ego frame
"""

from __future__ import annotations

import numpy as np

from occvo_core.cameras import RenderStyle, nuscenes_rig, render
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import grid_to_points
from occvo_core.models.tpvformer.predictor import OccupancyPredictor


class ImageOccupancySource:
    """SceneSource over any scene offering `true_grid(i)`, `times`/`rate_hz`, `gt_poses` (occvo_core.sim.SyntheticScene)."""

    def __init__(self, scene, predictor: OccupancyPredictor, style: RenderStyle = RenderStyle()):
        self.scene, self.predictor, self.style = scene, predictor, style
        self.rig = nuscenes_rig(*predictor.cfg.input_size)
        self.name = f"{getattr(scene, 'name', 'scene')}-from-images"
        self.rate_hz = float(scene.rate_hz)

    def __len__(self) -> int:
        return len(self.scene)

    @property
    def gt_poses(self) -> np.ndarray | None:
        return self.scene.gt_poses

    def camera_frame(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The six rendered images (6,H,W,3) uint8, intrinsics (6,3,3), cam_to_ego (6,4,4) of frame `index`."""
        seed = getattr(self.scene, "seed", 0)
        images = render(self.scene.true_grid(index), self.rig, self.style, rng=int(seed) * 100003 + index).images
        return images, self.rig.intrinsics, self.rig.cam_to_ego

    def __getitem__(self, index: int) -> OccupancyFrame:
        images, k, e = self.camera_frame(index)
        points, labels = grid_to_points(self.predictor.predict_grid(images, k, e))
        stamp = float(self.scene.times[index]) if hasattr(self.scene, "times") else index / self.rate_hz
        return OccupancyFrame(points, labels, index, stamp, {"scene": self.name, "source": "tpvformer"})
