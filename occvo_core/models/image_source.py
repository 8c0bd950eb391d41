"""Scene sources whose occupancy comes from the network: each frame's six camera images passed through TPV-Former
(images -> network -> odometry), rendered from a synthetic scene's true occupancy or a nuScenes drive's real JPEGs.

    scene = SyntheticScene(seed=0, frames=40)
    source = ImageOccupancySource(scene, OccupancyPredictor("checkpoint.pt"))
    frame = source[0]   # OccupancyFrame of the predicted occupied voxels, ego frame
    source = NuScenesImageSource(NuScenesDrive("../shared/data/nuscenes-mini"), predictor)
"""

from __future__ import annotations

import numpy as np

from occvo_core.cameras import RenderStyle, nuscenes_rig, render
from occvo_core.datasets.nuscenes_drive import DriveSource, NuScenesDrive
from occvo_core.errors import DatasetError
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


class NuScenesImageSource(DriveSource):
    """SceneSource: frame i = the network's occupancy from keyframe i's six real JPEGs, resized to the network's input
    size with the intrinsics scaled to match, the recorded cam_to_ego; stamped with the sample's stamp."""

    def __init__(self, drive: NuScenesDrive, predictor: OccupancyPredictor):
        super().__init__(drive, "from-images")
        self.predictor = predictor

    @property
    def stamps(self) -> np.ndarray:
        return self.drive.stamps

    def camera_frame(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The six images (6,H,W,3) uint8 at the network's input size, their intrinsics (6,3,3), cam_to_ego (6,4,4)."""
        from PIL import Image

        width, height = self.predictor.cfg.input_size
        rig = self.drive.rig(index).scaled(width, height)
        images = np.empty((6, height, width, 3), np.uint8)
        for c, path in enumerate(self.drive[index].files):
            try:
                with Image.open(path) as im:  # PIL's bilinear filter widens when shrinking: no aliasing
                    images[c] = np.asarray(im.convert("RGB").resize((width, height), Image.BILINEAR))
            except OSError as exc:
                raise DatasetError(path, f"unreadable camera image: {exc}") from None
        return images, rig.intrinsics, rig.cam_to_ego

    def grid(self, index: int) -> np.ndarray:
        """The predicted (200,200,16) label grid of keyframe `index` (the predictor's thresholds and mask)."""
        return self.predictor.predict_grid(*self.camera_frame(index))

    def __getitem__(self, index: int) -> OccupancyFrame:
        points, labels = grid_to_points(self.grid(index))
        meta = {"scene": self.name, "source": "tpvformer", "token": self.drive[index].token}
        return OccupancyFrame(points, labels, index, float(self.drive[index].stamp), meta)
