"""TPV-Former (Huang et al., CVPR 2023) in plain torch: six images -> tri-perspective view -> 200x200x16 occupancy."""

from occvo_core.models.tpvformer.checkpoint import (
    CheckpointError,
    CheckpointMismatchError,
    load_checkpoint,
    save_checkpoint,
    shipped_checkpoint,
)
from occvo_core.models.tpvformer.config import PRESETS, TPVFormerConfig, preset
from occvo_core.models.tpvformer.device import autocast, select_device
from occvo_core.models.tpvformer.model import TPVFormer
from occvo_core.models.tpvformer.predictor import InvalidCameraFrameError, OccupancyPredictor

__all__ = [
    "PRESETS",
    "CheckpointError",
    "CheckpointMismatchError",
    "InvalidCameraFrameError",
    "OccupancyPredictor",
    "TPVFormer",
    "TPVFormerConfig",
    "autocast",
    "load_checkpoint",
    "preset",
    "save_checkpoint",
    "select_device",
    "shipped_checkpoint",
]
