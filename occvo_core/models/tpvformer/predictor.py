"""Serving: camera frames in, occupancy grids (or OccupancyFrames) out; the inference worker wraps this."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from occvo_core.errors import OccVOError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import FREE, GROUND_CLASSES, OCC3D_GRID, GridSpec, grid_to_points
from occvo_core.models.camera_mask import masked
from occvo_core.models.tpvformer.checkpoint import load_checkpoint
from occvo_core.models.tpvformer.device import autocast, select_device


class InvalidCameraFrameError(OccVOError, ValueError):
    """Camera images or calibration that the network cannot take."""


def confident_labels(
    labels: torch.Tensor, confidence: torch.Tensor | None, min_confidence: float, min_ground_confidence: float
) -> torch.Tensor:
    """labels with every voxel whose confidence is below its threshold (ground classes: min_ground_confidence)
    set free; a threshold of 1 sets every voxel of its classes free (a softmax may round to exactly 1)."""
    if confidence is None or (min_confidence <= 0 and min_ground_confidence <= 0):
        return labels
    ground = torch.isin(labels, torch.tensor(GROUND_CLASSES, device=labels.device))
    threshold = torch.where(ground, min_ground_confidence, min_confidence)
    return labels.masked_fill((confidence < threshold) | (threshold >= 1.0), FREE)


class OccupancyPredictor:
    """Loads a checkpoint once; `predict_grid` maps six images + calibration to a uint8 (200,200,16) label grid.

    Also fits occvo_services.occupancy_model.OccupancyModel: `name`, `grid`, `predict` -> (voxel indices, labels).
    Images of another size than the checkpoint's input are resized and the intrinsics scaled to match.
    A voxel whose most likely class has a softmax probability below `min_confidence` (`min_ground_confidence` for
    the ground classes) is reported free: a network's unsure voxels are often ones it pins to the ego, and an
    odometry fed with them is pulled towards "no motion". With `camera_mask`, only the voxels the cameras' rays
    reach are kept (Occ3D's mask_camera, from the calibration given with the images).
    """

    def __init__(
        self,
        checkpoint: str | Path,
        device: str | None = None,
        min_confidence: float = 0.0,
        min_ground_confidence: float = 0.0,
        camera_mask: bool = False,
    ):
        for name, v in (("min_confidence", min_confidence), ("min_ground_confidence", min_ground_confidence)):
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        self.min_confidence, self.min_ground_confidence = float(min_confidence), float(min_ground_confidence)
        self.camera_mask = bool(camera_mask)
        self.device = select_device(device if device != "auto" else None)
        self.model = load_checkpoint(checkpoint, device=self.device)
        self.cfg = self.model.cfg
        self.grid = GridSpec(tuple(self.cfg.lower), tuple(self.cfg.upper), OCC3D_GRID.voxel_size)
        self.name = f"TPVFormer[{getattr(self.model, 'meta', {}).get('preset', '') or Path(checkpoint).stem}]"

    def predict(self, images, intrinsics, cam_to_ego) -> tuple[np.ndarray, np.ndarray]:
        """Sparse output: occupied voxel indices (N,3) and their labels (N,) uint8."""
        grid = self.predict_grid(
            np.stack(list(images)) if isinstance(images, (list, tuple)) else images, intrinsics, cam_to_ego
        )
        occupied = grid != FREE
        return np.argwhere(occupied), grid[occupied]

    def predict_grid(self, images: np.ndarray, intrinsics: np.ndarray, cam_to_ego: np.ndarray) -> np.ndarray:
        """images (6, H, W, 3) uint8 RGB; intrinsics (6, 3, 3) for that size; cam_to_ego (6, 4, 4)."""
        thresholds = self.min_confidence, self.min_ground_confidence
        labels, confidence = self.predict_labels(images, intrinsics, cam_to_ego, with_confidence=max(thresholds) > 0)
        grid = confident_labels(labels, confidence, *thresholds).to(torch.uint8).cpu().numpy()
        if self.camera_mask:
            grid = masked(grid, self.grid, intrinsics, cam_to_ego, (images.shape[2], images.shape[1]))
        return grid

    @torch.no_grad()
    def predict_labels(
        self, images: np.ndarray, intrinsics: np.ndarray, cam_to_ego: np.ndarray, with_confidence: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The most likely class of every voxel (200,200,16) and, with_confidence, its softmax probability; no
        threshold applied (predict_grid applies them)."""
        images, intrinsics, cam_to_ego = (
            np.asarray(images),
            np.asarray(intrinsics, np.float32),
            np.asarray(cam_to_ego, np.float32),
        )
        if images.ndim != 4 or images.shape[0] != 6 or images.shape[-1] != 3:
            raise InvalidCameraFrameError(f"images must be (6, H, W, 3), got {images.shape}")
        if images.dtype != np.uint8:
            raise InvalidCameraFrameError(f"images must be uint8 RGB, got {images.dtype}")
        if intrinsics.shape != (6, 3, 3) or cam_to_ego.shape != (6, 4, 4):
            raise InvalidCameraFrameError(
                f"calibration must be (6,3,3) and (6,4,4), got {intrinsics.shape} and {cam_to_ego.shape}"
            )
        if not (np.all(np.isfinite(intrinsics)) and np.all(np.isfinite(cam_to_ego))):
            raise InvalidCameraFrameError("calibration has non-finite values")
        if np.any(np.abs(np.linalg.det(cam_to_ego[:, :3, :3]) - 1) > 1e-3):
            raise InvalidCameraFrameError("cam_to_ego rotations are not proper rotations")
        x = torch.from_numpy(images).to(self.device).permute(0, 3, 1, 2).float().div_(255.0)
        w, h = self.cfg.input_size
        if x.shape[-2:] != (h, w):  # resize, keeping pixel centres consistent with the intrinsics
            sx, sy = w / x.shape[-1], h / x.shape[-2]
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
            intrinsics = intrinsics.copy()
            intrinsics[:, 0, 0] *= sx
            intrinsics[:, 1, 1] *= sy
            intrinsics[:, 0, 2] = (intrinsics[:, 0, 2] + 0.5) * sx - 0.5
            intrinsics[:, 1, 2] = (intrinsics[:, 1, 2] + 0.5) * sy - 0.5
        x = x[None]
        k = torch.from_numpy(intrinsics).to(self.device)[None]
        e = torch.from_numpy(cam_to_ego).to(self.device)[None]
        with autocast(self.device):
            logits = self.model(x, k, e)[0]
        return logits.argmax(0), (logits.float().softmax(0).amax(0) if with_confidence else None)

    def predict_frame(self, images, intrinsics, cam_to_ego, index: int = 0, stamp: float = 0.0) -> OccupancyFrame:
        points, labels = grid_to_points(self.predict_grid(images, intrinsics, cam_to_ego))
        return OccupancyFrame(points, labels, index, stamp, {"source": "tpvformer"})
