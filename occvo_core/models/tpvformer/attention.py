"""TPV-Former's two attentions, both deformable: sampled with `grid_sample` at learned offsets around reference points.

- ImageCrossAttention: each TPV query owns a set of 3D anchors (a pillar through its plane cell); the anchors are
  projected into every camera and the query samples that camera's multi-level features around the projections;
  cameras that see none of its anchors are skipped and the hits are averaged.
- CrossViewHybridAttention: the three planes attend to each other: a query samples its own plane around itself and
  the other two planes along the line its cell spans there.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

PLANES = ("hw", "zh", "wz")


def deformable_sample(values: list[torch.Tensor], locations: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Multi-level deformable sampling.

    values: L maps (N*M, Ch, H_l, W_l) for N items and M heads; locations (N, Q, M, L, P, 2) as (column, row) in
    [0, 1] (pixel edges, align_corners=False); weights (N, Q, M, L, P). Returns (N, Q, M*Ch); outside = zeros.
    """
    n, q, m, _, p, _ = locations.shape
    out = None
    for level, value in enumerate(values):
        grid = (2 * locations[:, :, :, level] - 1).permute(0, 2, 1, 3, 4).reshape(n * m, q, p, 2)
        sampled = F.grid_sample(value, grid, mode="bilinear", padding_mode="zeros", align_corners=False)  # (N*M, Ch, Q, P)
        w = weights[:, :, :, level].permute(0, 2, 1, 3).reshape(n * m, 1, q, p)
        term = (sampled * w).sum(-1)
        out = term if out is None else out + term
    ch = out.shape[1]
    return out.view(n, m, ch, q).permute(0, 3, 1, 2).reshape(n, q, m * ch)


def _init_offsets(linear: nn.Linear, heads: int, levels: int, points: int) -> None:
    """Deformable-DETR start: zero weights, biases spreading each head's points along its own direction."""
    nn.init.zeros_(linear.weight)
    theta = torch.arange(heads, dtype=torch.float32) * (2 * math.pi / heads)
    grid = torch.stack([theta.cos(), theta.sin()], -1)
    grid = grid / grid.abs().max(-1, keepdim=True).values
    grid = grid.view(heads, 1, 1, 2).repeat(1, levels, points, 1)
    grid *= torch.arange(1, points + 1, dtype=torch.float32).view(1, 1, points, 1) / points * 2
    with torch.no_grad():
        linear.bias.copy_(grid.reshape(-1))


class ImageCrossAttention(nn.Module):
    """Per plane p: queries (B, Q_p, C) sample camera features around their projected anchors (Q_p, D_p)."""

    def __init__(self, embed_dims: int, num_heads: int, num_levels: int, anchors: tuple[int, ...], points: tuple[int, ...],
                 query_chunk: int = 16384):
        super().__init__()
        self.c, self.m, self.l = embed_dims, num_heads, num_levels
        self.anchors, self.points, self.query_chunk = tuple(anchors), tuple(points), query_chunk
        self.value_proj = nn.Linear(embed_dims, embed_dims)
        self.sampling_offsets = nn.ModuleList(nn.Linear(embed_dims, num_heads * num_levels * p * 2) for p in points)
        self.attention_weights = nn.ModuleList(nn.Linear(embed_dims, num_heads * num_levels * p) for p in points)
        self.output_proj = nn.ModuleList(nn.Linear(embed_dims, embed_dims) for _ in points)
        for off, att, p in zip(self.sampling_offsets, self.attention_weights, points):
            _init_offsets(off, num_heads, num_levels, p)
            nn.init.zeros_(att.weight)
            nn.init.zeros_(att.bias)

    def forward(self, queries: list[torch.Tensor], pos: list[torch.Tensor], feats: list[torch.Tensor],
                ref_uv: list[torch.Tensor], ref_valid: list[torch.Tensor]) -> list[torch.Tensor]:
        """feats: L levels (B, Ncam, C, H_l, W_l); ref_uv[p] (B, Ncam, Q_p, D_p, 2) normalised (column, row) in [0, 1];
        ref_valid[p] (B, Ncam, Q_p, D_p): anchor in front of the camera and inside its image."""
        b, ncam = feats[0].shape[:2]
        ch = self.c // self.m
        values, norms = [], []
        for f in feats:
            h, w = f.shape[-2:]
            v = self.value_proj(f.permute(0, 1, 3, 4, 2))  # (B, Ncam, H, W, C)
            values.append(v.view(b, ncam, h, w, self.m, ch).permute(0, 1, 4, 5, 2, 3))  # (B, Ncam, M, Ch, H, W)
            norms.append(torch.tensor([w, h], dtype=f.dtype, device=f.device))
        norm = torch.stack(norms).view(1, 1, self.l, 1, 1, 2)  # against (q, M, L, D, P/D, 2)
        outputs = []
        for p, (q, qpos) in enumerate(zip(queries, pos)):
            nq, d, npts = q.shape[1], self.anchors[p], self.points[p]
            x = q + qpos
            offsets = self.sampling_offsets[p](x).view(b, nq, self.m, self.l, d, npts // d, 2)
            weights = self.attention_weights[p](x).view(b, nq, self.m, self.l * npts).softmax(-1).view(b, nq, self.m, self.l, npts)
            acc = [q.new_zeros(nq, self.c) for _ in range(b)]
            count = q.new_zeros(b, nq, 1)
            for bi in range(b):
                for cam in range(ncam):
                    hit = ref_valid[p][bi, cam].any(-1).nonzero().squeeze(1)
                    cam_values = [v[bi, cam].reshape(self.m, ch, *v.shape[-2:]) for v in values]
                    for idx in hit.split(self.query_chunk):
                        ref = ref_uv[p][bi, cam, idx]  # (q, D, 2)
                        loc = ref[:, None, None, :, None, :] + offsets[bi, idx] / norm
                        loc = loc.reshape(1, len(idx), self.m, self.l, npts, 2)
                        sampled = deformable_sample(cam_values, loc, weights[bi, idx].unsqueeze(0))[0]
                        acc[bi] = acc[bi].index_add(0, idx, sampled)
                        count[bi, idx] += 1
            outputs.append(self.output_proj[p](torch.stack(acc) / count.clamp(min=1)))
        return outputs


class CrossViewHybridAttention(nn.Module):
    """Deformable self attention over the three planes taken as three value maps (levels)."""

    def __init__(self, embed_dims: int, num_heads: int, points: int, query_chunk: int = 16384):
        super().__init__()
        self.c, self.m, self.p, self.query_chunk = embed_dims, num_heads, points, query_chunk
        self.value_proj = nn.Linear(embed_dims, embed_dims)
        self.sampling_offsets = nn.ModuleList(nn.Linear(embed_dims, num_heads * 3 * points * 2) for _ in PLANES)
        self.attention_weights = nn.ModuleList(nn.Linear(embed_dims, num_heads * 3 * points) for _ in PLANES)
        self.output_proj = nn.ModuleList(nn.Linear(embed_dims, embed_dims) for _ in PLANES)
        for off, att in zip(self.sampling_offsets, self.attention_weights):
            _init_offsets(off, num_heads, 3, points)
            nn.init.zeros_(off.weight)
            with torch.no_grad():
                off.bias.mul_(0.25)  # start close to the reference lines
            nn.init.zeros_(att.weight)
            nn.init.zeros_(att.bias)

    def forward(self, queries: list[torch.Tensor], pos: list[torch.Tensor], shape: tuple[int, int, int],
                ref: list[torch.Tensor]) -> list[torch.Tensor]:
        """queries[p] (B, Q_p, C) for HW, ZH, WZ; ref[p] (Q_p, 3, A, 2): anchors of each query on each plane map."""
        h, w, z = shape
        b, ch = queries[0].shape[0], self.c // self.m
        maps = [(h, w), (z, h), (w, z)]  # (rows, cols) of the HW, ZH, WZ planes
        values = []
        for q, (rows, cols) in zip(queries, maps):
            v = self.value_proj(q).view(b, rows, cols, self.m, ch).permute(0, 3, 4, 1, 2)
            values.append(v.reshape(b * self.m, ch, rows, cols))
        norm = torch.tensor([[c, r] for r, c in maps], dtype=queries[0].dtype, device=queries[0].device).view(1, 1, 1, 3, 1, 1, 2)
        outputs = []
        for p, (q, qpos) in enumerate(zip(queries, pos)):
            nq, a = q.shape[1], ref[p].shape[2]
            x = q + qpos
            offsets = self.sampling_offsets[p](x).view(b, nq, self.m, 3, a, self.p // a, 2)
            weights = self.attention_weights[p](x).view(b, nq, self.m, 3 * self.p).softmax(-1).view(b, nq, self.m, 3, self.p)
            chunks = []
            for s in range(0, nq, self.query_chunk):
                e = min(nq, s + self.query_chunk)
                loc = ref[p][None, s:e, None, :, :, None, :] + offsets[:, s:e] / norm
                loc = loc.reshape(b, e - s, self.m, 3, self.p, 2)
                chunks.append(deformable_sample(values, loc, weights[:, s:e]))
            outputs.append(self.output_proj[p](torch.cat(chunks, 1)))
        return outputs
