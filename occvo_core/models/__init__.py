"""Neural front ends: surround images -> 3D semantic occupancy (TPV-Former)."""

from occvo_core.models.tpvformer import TPVFormer, TPVFormerConfig, load_checkpoint, preset, save_checkpoint

__all__ = ["TPVFormer", "TPVFormerConfig", "load_checkpoint", "preset", "save_checkpoint"]
