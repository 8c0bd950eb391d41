"""TPV-Former's training losses: weighted cross entropy with Lovasz-softmax on the occupancy, an image auxiliary
head, and depth supervision along the camera rays."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from occvo_core.grid import NUM_CLASSES


def _lovasz_grad(gt_sorted: torch.Tensor) -> torch.Tensor:
    gts = gt_sorted.sum()
    intersection = gts - gt_sorted.cumsum(0)
    union = gts + (1 - gt_sorted).cumsum(0)
    jaccard = 1.0 - intersection / union
    jaccard[1:] = jaccard[1:] - jaccard[:-1]
    return jaccard


def lovasz_softmax(probs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Lovasz-softmax (Berman et al., CVPR 2018) over the classes present: probs (P, C), labels (P,)."""
    losses = []
    for c in labels.unique():
        fg = (labels == c).float()
        errors = (fg - probs[:, c]).abs()
        errors_sorted, perm = torch.sort(errors, descending=True)
        losses.append(torch.dot(errors_sorted, _lovasz_grad(fg[perm])))
    return torch.stack(losses).mean() if losses else probs.sum() * 0


def class_weights(frequencies: np.ndarray) -> torch.Tensor:
    """Inverse log frequency: rare classes weigh up to ~10x free space."""
    f = np.asarray(frequencies, np.float64) / max(1, np.sum(frequencies))
    return torch.tensor(1.0 / np.log(1.1 + f), dtype=torch.float32)


def occupancy_loss(
    logits: torch.Tensor,
    semantics: torch.Tensor,
    mask: torch.Tensor,
    weights: torch.Tensor,
    outside_weight: float = 0.1,
    lovasz_voxels: int = 32768,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, dict]:
    """Weighted cross entropy on camera-visible voxels (plus the rest at `outside_weight`) + Lovasz-softmax on a random
    subset of the visible voxels (the sort over every voxel would dominate a CPU step).

    logits (B, C, X, Y, Z), semantics (B, X, Y, Z) long, mask (B, X, Y, Z) bool.
    """
    c = logits.shape[1]
    voxels = logits.permute(0, 2, 3, 4, 1).reshape(-1, c)  # the model's logits are channels-last in memory: no copy
    visible = mask.reshape(-1)
    # Voxels outside the mask enter with probability `outside_weight` instead of at that weight: the same loss in
    # expectation, at a third of the cost of a log-softmax over every voxel.
    kept = visible | (torch.rand(visible.shape, generator=generator, device=visible.device) < outside_weight)
    ce = F.cross_entropy(
        voxels[kept].float(), semantics.reshape(-1)[kept], weight=weights, reduction="sum"
    ) / kept.sum().clamp(min=1)
    idx = visible.nonzero().squeeze(1)
    if len(idx) > lovasz_voxels:
        idx = idx[torch.randperm(len(idx), generator=generator, device=idx.device)[:lovasz_voxels]]
    flat, labels = voxels[idx], semantics.reshape(-1)[idx]
    lovasz = lovasz_softmax(flat.float().softmax(-1), labels)
    return ce + lovasz, {"ce": float(ce.detach()), "lovasz": float(lovasz.detach())}


class ImageAuxHead(nn.Module):
    """Training-only head on the finest FPN level: per-pixel class of the first voxel hit (17 classes + none).

    The synthetic renderer knows it for every pixel; supervising it teaches the backbone what it sees before the
    occupancy loss has to. Not part of the checkpoint: inference never runs it.
    """

    def __init__(self, channels: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(channels, NUM_CLASSES, 1)
        )

    def loss(self, feature: torch.Tensor, labels: np.ndarray, sparse: bool = False) -> torch.Tensor:
        """feature (Ncam, C, h, w) of one sample; labels (Ncam, H, W) at image resolution, 255 = no hit; `sparse`
        (a real camera's LiDAR returns): 255 = unknown, left out."""
        out = F.interpolate(self.net(feature), size=labels.shape[-2:], mode="bilinear", align_corners=False)
        lab = torch.from_numpy(labels.astype(np.int64)).to(out.device)
        if sparse:
            return F.cross_entropy(out.float(), lab, ignore_index=255)
        lab[lab == 255] = NUM_CLASSES - 1  # no hit: the free class
        return F.cross_entropy(out.float(), lab)


def depth_loss(
    depth_logits: torch.Tensor, ray_length: np.ndarray, intrinsics: torch.Tensor, depth_range: tuple[float, float]
) -> torch.Tensor:
    """Cross entropy of the depth head's log-spaced bins (Ncam, bins, h, w) against the rendered depth (Ncam, H, W)
    (ray length, turned into depth along the optical axis as the anchors use it); rays without a hit are ignored."""
    ncam, bins = depth_logits.shape[:2]
    h, w = ray_length.shape[-2:]
    out = F.interpolate(depth_logits.float(), size=(h, w), mode="bilinear", align_corners=False)
    dev = out.device
    r = torch.from_numpy(np.asarray(ray_length, np.float32)).to(dev)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float32, device=dev),
        torch.arange(w, dtype=torch.float32, device=dev),
        indexing="ij",
    )
    fx, fy, cx, cy = (intrinsics[:, i, j].to(dev).view(-1, 1, 1) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    z = r / torch.sqrt(((u - cx) / fx) ** 2 + ((v - cy) / fy) ** 2 + 1)
    near, far = depth_range
    target = (torch.log(z.clamp(near, far) / near) / math.log(far / near) * bins).long().clamp(0, bins - 1)
    target[~torch.isfinite(r)] = -100
    return F.cross_entropy(out, target, ignore_index=-100)
