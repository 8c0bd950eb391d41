"""The seam between camera frames and occupancy: the `OccupancyModel` interface and the networks behind it.

`load_occupancy_model(checkpoint, model_weights, device)` picks the network of the inference worker's `model` source:
  checkpoint     the trained TPV-Former (occvo_core.models.tpvformer.OccupancyPredictor; `occvo train-occ` writes one)
  model_weights  `TinyOccNet` with its saved state_dict: a small real camera-to-voxel net (shared conv encoder per
                 camera, cameras fused, a BEV head on a coarse 50 x 50 x 4 volume repeated up to the 200 x 200 x 16 grid)
Neither: a ConfigError. An untrained network's voxels would flow into the odometry as if they were a prediction.
"""

from __future__ import annotations

import io
from typing import Protocol

import numpy as np
import torch
from torch import nn

from occvo_core.errors import ConfigError
from occvo_core.grid import FREE, NUM_CLASSES, OCC3D_GRID, GridSpec
from occvo_schemas.models import CameraImage

RGB_MODES = ("RGB", "RGBA")  # 8 bits a channel; alpha is dropped. Grey or 16-bit images are refused, not guessed at.


def decode_image(img: CameraImage) -> np.ndarray:
    """(H, W, 3) uint8 RGB; ValueError naming the camera when the bytes do not decode to an 8-bit colour image of the
    declared size."""
    if img.encoding == "raw_rgb8":
        return np.frombuffer(img.data, np.uint8).reshape(img.height, img.width, 3)
    from PIL import Image

    try:
        with Image.open(io.BytesIO(img.data)) as im:
            fmt, mode = im.format, im.mode
            if fmt != img.encoding.upper():
                raise ValueError(f"the bytes are {fmt or 'no known image format'}")
            if mode not in RGB_MODES:
                raise ValueError(f"pixel mode {mode}; the model takes 8-bit RGB")
            rgb = np.asarray(im.convert("RGB"))
    except Exception as exc:  # noqa: BLE001 - PIL raises many types on bad bytes
        raise ValueError(f"camera {img.camera}: cannot decode {img.encoding}: {exc}") from None
    if rgb.shape[:2] != (img.height, img.width):
        raise ValueError(
            f"camera {img.camera}: decoded {rgb.shape[1]}x{rgb.shape[0]}, message says {img.width}x{img.height}"
        )
    return rgb


def encode_image(rgb: np.ndarray, camera: str, intrinsics, extrinsics, encoding: str = "jpeg") -> CameraImage:
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if encoding == "raw_rgb8":
        data = rgb.tobytes()
    else:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(rgb).save(buf, format=encoding.upper(), quality=90) if encoding == "jpeg" else Image.fromarray(
            rgb
        ).save(buf, format="PNG")
        data = buf.getvalue()
    return CameraImage(
        camera=camera,
        encoding=encoding,
        width=rgb.shape[1],
        height=rgb.shape[0],
        data=data,
        intrinsics=np.asarray(intrinsics, float).tolist(),
        extrinsics=np.asarray(extrinsics, float).tolist(),
    )


class OccupancyModel(Protocol):
    name: str
    grid: GridSpec

    def predict(
        self, images: list[np.ndarray], intrinsics: np.ndarray, extrinsics: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """6 RGB images (H,W,3) uint8, K (6,3,3), camera-to-ego (6,4,4) -> (voxel indices (N,3) int, labels (N,) uint8)."""
        ...


class TinyOccNet(nn.Module):
    def __init__(self, cams: int = 6, coarse: tuple[int, int, int] = (50, 50, 4), width: int = 32):
        super().__init__()
        self.coarse = coarse
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 16, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(16, width, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(width, width, 3, stride=2, padding=1),
            nn.ReLU(),
        )
        self.fuse = nn.Conv2d(cams * width, 64, 1)
        self.head = nn.Conv2d(64, NUM_CLASSES * coarse[2], 3, padding=1)
        with torch.no_grad():  # start from "mostly free", as a real occupancy prior would
            self.head.bias.view(NUM_CLASSES, coarse[2])[FREE] += 4.0

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, 6, 3, H, W) in [0, 1] -> logits (B, 18, X, Y, Z) on the coarse volume."""
        b, c = images.shape[:2]
        f = self.encoder(images.flatten(0, 1).contiguous())  # (B*6, w, h', w')
        f = f.reshape(b, c * f.shape[1], *f.shape[2:])
        f = torch.relu(self.fuse(f))
        f = nn.functional.adaptive_avg_pool2d(f, self.coarse[:2])  # BEV (X, Y)
        logits = self.head(f).reshape(b, NUM_CLASSES, self.coarse[2], *self.coarse[:2])
        return logits.permute(0, 1, 3, 4, 2)


def select_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' asked for but torch sees no CUDA device; use 'cpu' or 'auto'")
    return torch.device(device)


class TorchOccupancyModel:
    """Runs a torch occupancy network on one camera frame and returns sparse voxels on the Occ3D grid."""

    def __init__(
        self,
        net: nn.Module | None = None,
        device: str = "auto",
        weights: str | None = None,
        input_hw: tuple[int, int] = (96, 160),
        grid: GridSpec = OCC3D_GRID,
        seed: int = 0,
    ):
        torch.manual_seed(seed)  # untrained weights are reproducible
        self.net = net if net is not None else TinyOccNet()
        if weights:
            self.net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
        self.device = select_device(device)
        self.net.to(self.device).eval()
        self.input_hw = input_hw
        self.grid = grid
        self.name = type(self.net).__name__

    @torch.inference_mode()
    def predict(self, images, intrinsics, extrinsics):
        x = torch.from_numpy(np.stack(images)).to(self.device).permute(0, 3, 1, 2).float() / 255.0
        x = nn.functional.interpolate(x, size=self.input_hw, mode="bilinear", align_corners=False)
        labels = self.net(x.unsqueeze(0)).argmax(1)[0]  # (X, Y, Z) coarse
        gx, gy, gz = self.grid.shape
        rep = (gx // labels.shape[0], gy // labels.shape[1], gz // labels.shape[2])
        full = (
            labels.repeat_interleave(rep[0], 0).repeat_interleave(rep[1], 1).repeat_interleave(rep[2], 2).cpu().numpy()
        )
        idx = np.argwhere(full != FREE)
        return idx, full[full != FREE].astype(np.uint8)


def camera_inputs(images: list[CameraImage]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Six wire images -> (6, H, W, 3) uint8, K (6, 3, 3), camera-to-ego (6, 4, 4); ValueError naming what is wrong."""
    if len(images) != 6:
        raise ValueError(f"the model source needs 6 camera images, got {len(images)}")
    rgb = [decode_image(im) for im in images]
    sizes = {f"{a.shape[1]}x{a.shape[0]}" for a in rgb}
    if len(sizes) > 1:
        raise ValueError(
            f"the 6 camera images differ in size ({', '.join(f'{im.camera} {im.width}x{im.height}' for im in images)})"
        )
    return np.stack(rgb), np.array([im.intrinsics for im in images]), np.array([im.extrinsics for im in images])


def load_occupancy_model(
    checkpoint: str | None = None,
    model_weights: str | None = None,
    device: str = "auto",
    min_confidence: float = 0.0,
    min_ground_confidence: float = 0.0,
    camera_mask: bool = False,
) -> OccupancyModel:
    """The network of the worker's `model` source, or a ConfigError naming what is wrong (file, format, shapes)."""
    if checkpoint and model_weights:
        raise ConfigError("give checkpoint (TPV-Former) or model_weights (TinyOccNet), not both")
    if not checkpoint and not model_weights:
        raise ConfigError(
            "source 'model' needs checkpoint: a TPV-Former checkpoint from `occvo train-occ` "
            "(--checkpoint PATH, or `checkpoint` in the worker config)"
        )
    dev = str(select_device(device))
    if model_weights:
        try:
            return TorchOccupancyModel(device=dev, weights=model_weights)
        except Exception as exc:  # noqa: BLE001 - missing file, pickle or shape errors: one clear line
            raise ConfigError(
                f"model_weights {model_weights}: not TinyOccNet weights ({type(exc).__name__}: {exc})"
            ) from None
    from occvo_core.models.tpvformer import CheckpointError, OccupancyPredictor

    try:
        model = OccupancyPredictor(
            checkpoint,
            device=dev,
            min_confidence=min_confidence,
            min_ground_confidence=min_ground_confidence,
            camera_mask=camera_mask,
        )
    except CheckpointError as exc:
        raise ConfigError(f"checkpoint {exc}") from None
    if model.cfg.num_classes != NUM_CLASSES:  # the wire carries Occ3D class ids
        raise ConfigError(
            f"checkpoint {checkpoint}: {model.cfg.num_classes} classes, the service needs the {NUM_CLASSES} Occ3D classes"
        )
    if max(model.grid.shape) > 65535:
        raise ConfigError(f"checkpoint {checkpoint}: grid {model.grid.shape} too large for uint16 voxel indices")
    return model
