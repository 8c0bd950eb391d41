"""The label prior: how often each voxel of the ego-frame grid was occupied in a drive's training labels, as an
initial per-voxel offset of the network's free logit (TPVFormerConfig.label_prior). A parking-lot drive's ground and
walls sit at much the same place around the car from keyframe to keyframe; the offset gives the network that place
to start from, and training moves it with the rest of the weights."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from occvo_core.grid import FREE


def occupancy_frequency(semantics: np.ndarray) -> np.ndarray:
    """(n, X, Y, Z) label grids -> (X, Y, Z) share of them occupied at each voxel (over all n, seen or not)."""
    if semantics.ndim != 4 or not len(semantics):
        raise ValueError(f"label grids must be (n, X, Y, Z) with n > 0, got {semantics.shape}")
    return (semantics != FREE).mean(0)


def free_prior(
    frequency: np.ndarray, shape: tuple[int, int, int], threshold: float, weight: float, clip: float = 4.0
) -> torch.Tensor:
    """The free logit's offset at `shape` (the decoder's resolution): `weight` times the free log-odds of the
    voxel's frequency (averaged down to `shape`) less those of `threshold`, so that at weight 1 alone it calls
    occupied what the frequency puts at `threshold` or above; clipped to +-`clip`."""
    if not 0 < threshold < 1:
        raise ValueError(f"threshold must be in (0, 1), got {threshold}")
    p = torch.from_numpy(np.asarray(frequency, np.float32))[None, None]
    p = F.adaptive_avg_pool3d(p, shape)[0, 0].clamp(0.01, 0.99)
    odds = torch.log((1 - p) / p) - float(np.log((1 - threshold) / threshold))
    return (weight * odds).clamp(-clip, clip)


def with_label_prior(src, dst, prior: torch.Tensor):
    """src's checkpoint with a label prior added (or replaced): the prior alone, before any training moves it."""
    from occvo_core.models.tpvformer.checkpoint import read_checkpoint, save_checkpoint
    from occvo_core.models.tpvformer.config import TPVFormerConfig
    from occvo_core.models.tpvformer.model import TPVFormer

    payload = read_checkpoint(src)
    cfg = TPVFormerConfig.model_validate({**payload["config"], "label_prior": True})
    model = TPVFormer(cfg)
    state = {k: v.float() if v.is_floating_point() else v for k, v in payload["state_dict"].items()}
    model.load_state_dict({**state, "free_prior": prior}, strict=True)
    return save_checkpoint(dst, model, payload.get("meta", {}))
