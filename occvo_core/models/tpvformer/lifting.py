"""Depth lifting (as in Lift-Splat-Shoot): each pixel's most likely depth, from the depth head trained on projected
LiDAR, put back along the pixel's ray into the ego frame, and the voxels those points land in.

The voxel decoder learns, from a few keyframes, where things tend to be around the car; the depth head reads each
pixel. Occupancy gated by the lifted voxels moves with what the images show, so it moves with the world.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def lifted_points(
    depth_prob: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_to_ego: torch.Tensor,
    image_hw: tuple[int, int],
    depth_range: tuple[float, float],
    upsample: int = 4,
) -> torch.Tensor:
    """depth_prob (Ncam, bins, h, w) over log-spaced bins, intrinsics (Ncam, 3, 3) and cam_to_ego (Ncam, 4, 4) of the
    (ih, iw) images -> ego points (Ncam, H, W, 3) at each pixel's most likely depth (the distribution upsampled
    bilinearly `upsample` times; the depth refined by the mode bin's two neighbours, in log depth)."""
    ncam, bins, h, w = depth_prob.shape
    ih, iw = image_hw
    prob = F.interpolate(depth_prob.float(), scale_factor=upsample, mode="bilinear", align_corners=False)
    hh, ww = prob.shape[-2:]
    mode = prob.argmax(1, keepdim=True)
    near, far = depth_range
    step = math.log(far / near) / bins
    idx = torch.cat([(mode - 1).clamp(0, bins - 1), mode, (mode + 1).clamp(0, bins - 1)], 1)
    p = prob.gather(1, idx)
    t = (idx.float() + 0.5) * step  # log(depth / near) of each bin's centre
    z = near * torch.exp((p * t).sum(1) / p.sum(1).clamp(min=1e-9))  # (Ncam, H, W): depth along the optical axis
    dev = z.device
    v, u = torch.meshgrid(
        (torch.arange(hh, device=dev) + 0.5) * ih / hh - 0.5,
        (torch.arange(ww, device=dev) + 0.5) * iw / ww - 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], -1)  # (H, W, 3)
    rays = torch.einsum("nij,hwj->nhwi", torch.linalg.inv(intrinsics.float()), pix)
    cam = rays * z[..., None]
    return torch.einsum("nij,nhwj->nhwi", cam_to_ego[:, :3, :3].float(), cam) + cam_to_ego[:, None, None, :3, 3].float()


def lifted_voxels(
    points: torch.Tensor,
    lower: tuple[float, float, float],
    upper: tuple[float, float, float],
    shape: tuple[int, int, int],
    max_range: float,
) -> torch.Tensor:
    """Ego points (..., 3) -> bool (X, Y, Z): the grid's voxels holding a point within `max_range` m of the ego
    (horizontally); farther points, where a pixel spans metres, are left out."""
    pts = points.reshape(-1, 3)
    lo, hi = torch.tensor(lower, device=pts.device), torch.tensor(upper, device=pts.device)
    size = (hi - lo) / torch.tensor(shape, device=pts.device)
    ijk = torch.floor((pts - lo) / size).long()
    dims = torch.tensor(shape, device=pts.device)
    keep = ((ijk >= 0) & (ijk < dims)).all(-1) & (pts[:, :2].norm(dim=-1) <= max_range)
    ijk = ijk[keep]
    grid = torch.zeros(shape, dtype=torch.bool, device=pts.device)
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return grid
