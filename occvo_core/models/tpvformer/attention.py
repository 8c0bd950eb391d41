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
        # Points along the rows of the grid, queries along its columns: the weighted sum runs over a middle dimension
        # with contiguous queries inside (a sum over a short last dimension is several times slower on CPU).
        grid = (2 * locations[:, :, :, level] - 1).permute(0, 2, 3, 1, 4).reshape(n * m, p, q, 2)
        sampled = F.grid_sample(
            value, grid, mode="bilinear", padding_mode="zeros", align_corners=False
        )  # (N*M, Ch, P, Q)
        w = weights[:, :, :, level].permute(0, 2, 3, 1).reshape(n * m, 1, p, q)
        term = (sampled * w).sum(2)
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


def tile_cameras(values: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """L levels (Ncam, M, Ch, H_l, W_l) -> one zero-separated map (M, Ch, H_t, W_t): cameras stacked down, levels
    side by side, a zero row/column around every tile. Returns it with the tile origins: x per level (L,), y per
    camera (Ncam,), in tile-map pixels. One `grid_sample` then reads any camera and level; a location clamped to
    one pixel outside its tile reads zeros there, exactly like zero padding on the camera's own map."""
    ncam = values[0].shape[0]
    hmax = max(v.shape[-2] for v in values)
    cols, ox, x = [], [], 1
    for v in values:
        h, w = v.shape[-2:]
        cols.append(F.pad(v, (1, 0, 0, hmax + 1 - h)))
        ox.append(x)
        x += w + 1
    tiled = F.pad(torch.cat(cols, -1), (0, 1))  # (Ncam, M, Ch, Hmax+1, W_t)
    ncam, m, ch, hb, wt = tiled.shape
    tiled = F.pad(tiled.permute(1, 2, 0, 3, 4).reshape(m, ch, ncam * hb, wt), (0, 0, 1, 0))
    dev = tiled.device
    return tiled, torch.tensor(ox, device=dev), 1 + hb * torch.arange(ncam, device=dev)


class ImageCrossAttention(nn.Module):
    """Per plane p: queries (B, Q_p, C) sample camera features around their projected anchors (Q_p, D_p).

    With `visible_anchors_only` a query samples around only those of its anchors that land in the camera's image;
    otherwise (as published) around all its anchors in every camera that sees at least one of them.
    """

    def __init__(
        self,
        embed_dims: int,
        num_heads: int,
        num_levels: int,
        anchors: tuple[int, ...],
        points: tuple[int, ...],
        query_chunk: int = 16384,
        visible_anchors_only: bool = False,
        depth_range: tuple[float, float] = (1.0, 80.0),
    ):
        super().__init__()
        self.depth_range = depth_range
        self.c, self.m, self.l = embed_dims, num_heads, num_levels
        self.anchors, self.points, self.query_chunk = tuple(anchors), tuple(points), query_chunk
        self.visible_anchors_only = visible_anchors_only
        self.value_proj = nn.Linear(embed_dims, embed_dims)
        self.sampling_offsets = nn.ModuleList(nn.Linear(embed_dims, num_heads * num_levels * p * 2) for p in points)
        self.attention_weights = nn.ModuleList(nn.Linear(embed_dims, num_heads * num_levels * p) for p in points)
        self.output_proj = nn.ModuleList(nn.Linear(embed_dims, embed_dims) for _ in points)
        for off, att, p in zip(self.sampling_offsets, self.attention_weights, points):
            _init_offsets(off, num_heads, num_levels, p)
            nn.init.zeros_(att.weight)
            nn.init.zeros_(att.bias)

    def forward(
        self,
        queries: list[torch.Tensor],
        pos: list[torch.Tensor],
        feats: list[torch.Tensor],
        ref_uv: list[torch.Tensor],
        ref_valid: list[torch.Tensor],
        ref_depth: list[torch.Tensor] | None = None,
        depth_prob: torch.Tensor | None = None,
    ) -> list[torch.Tensor]:
        """feats: L levels (B, Ncam, C, H_l, W_l); ref_uv[p] (B, Ncam, Q_p, D_p, 2) normalised (column, row) in [0, 1];
        ref_valid[p] (B, Ncam, Q_p, D_p): anchor in front of the camera and inside its image.

        Depth-aware (with ref_depth[p] (B, Ncam, Q_p, D_p) the anchors' depths and depth_prob (B, Ncam, bins, h, w) the
        image's depth distribution over log-spaced bins): what an anchor samples is weighted by the probability that
        the surface seen at its pixel lies at its depth, so a cell in front of a wall does not take the wall's features.
        """
        b, ncam = feats[0].shape[:2]
        ch = self.c // self.m
        values = []
        for f in feats:
            h, w = f.shape[-2:]
            v = self.value_proj(f.permute(0, 1, 3, 4, 2))  # (B, Ncam, H, W, C)
            values.append(v.view(b, ncam, h, w, self.m, ch).permute(0, 1, 4, 5, 2, 3))  # (B, Ncam, M, Ch, H, W)
        dev, dt = feats[0].device, feats[0].dtype
        size = torch.tensor([[f.shape[-1], f.shape[-2]] for f in feats], dtype=dt, device=dev).view(1, 1, self.l, 1, 2)
        outputs = []
        for p, (q, qpos) in enumerate(zip(queries, pos)):
            nq, d, npts = q.shape[1], self.anchors[p], self.points[p]
            x = q + qpos
            k = self.l * (npts // d)  # sampling points per head, anchor and camera over all levels
            # Rows (query, anchor): offsets (M, L, P/D, 2) and weights (M, L, P/D) of each, gathered per entry below.
            offsets = (
                self.sampling_offsets[p](x).view(b, nq, self.m, self.l, d, npts // d, 2).permute(0, 1, 4, 2, 3, 5, 6)
            )
            offsets = offsets.reshape(b, nq * d, self.m, self.l, npts // d, 2)
            weights = self.attention_weights[p](x).view(b, nq, self.m, self.l * npts).softmax(-1)
            weights = (
                weights.view(b, nq, self.m, self.l, d, npts // d)
                .permute(0, 1, 4, 2, 3, 5)
                .reshape(b, nq * d, self.m, k)
            )
            out = []
            for bi in range(b):
                tiled, ox, oy = tile_cameras([v[bi] for v in values])
                if depth_prob is not None:  # one volume (1, 1, bins, H_t, W_t): cameras tiled as the features are
                    dtiled, _, doy = tile_cameras([depth_prob[bi][:, None]])
                    dsize = torch.tensor([depth_prob.shape[-1], depth_prob.shape[-2]], dtype=dt, device=dev)
                    dhw = torch.tensor([dtiled.shape[-1], dtiled.shape[-2]], dtype=dt, device=dev)
                    dtiled = dtiled[None]
                hw = torch.tensor([tiled.shape[-1], tiled.shape[-2]], dtype=dt, device=dev)
                valid = ref_valid[p][bi]  # (Ncam, Q, D)
                hit = valid.any(-1)  # cameras that see at least one anchor of the query
                entries = valid if self.visible_anchors_only else hit[..., None].expand_as(valid)
                uv = ref_uv[p][bi].reshape(-1, 2)
                acc = q.new_zeros(nq, self.c)
                # Entries (camera, query, anchor), all sampled by one grid_sample over the tiled cameras and levels.
                for chunk in entries.nonzero().split(self.query_chunk):
                    cam, qi, di = chunk.unbind(1)
                    t, qd = len(cam), qi * d + di
                    px = uv[cam * nq * d + qd][:, None, None, None] * size + offsets[bi][qd] - 0.5  # level pixels
                    px = torch.maximum(
                        torch.minimum(px, size), torch.full_like(size, -1.0)
                    )  # zeros outside, as padding
                    origin = torch.stack([ox.view(1, self.l).expand(t, -1), oy[cam, None].expand(-1, self.l)], -1)
                    px = px + origin[:, None, :, None].to(dt)
                    grid = (2 * (px + 0.5) / hw - 1).permute(1, 2, 3, 0, 4).reshape(self.m, k, t, 2)
                    sampled = F.grid_sample(tiled, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
                    term = (sampled * weights[bi][qd].permute(1, 2, 0)[:, None]).sum(2)  # (M, Ch, T)
                    if depth_prob is not None:
                        near, far = self.depth_range
                        z = ref_depth[p][bi][cam, qi, di].clamp(near, far)
                        z = 2 * torch.log(z / near) / math.log(far / near) - 1  # bin axis of the volume, in [-1, 1]
                        dpx = uv[cam * nq * d + qd] * dsize - 0.5
                        dpx = torch.maximum(torch.minimum(dpx, dsize), torch.full_like(dsize, -1.0))
                        dpx = dpx + torch.stack([torch.ones_like(z), doy[cam].to(dt)], -1)
                        g = torch.cat([2 * (dpx + 0.5) / dhw - 1, z[:, None]], -1).view(1, t, 1, 1, 3)
                        prob = F.grid_sample(dtiled, g, mode="bilinear", padding_mode="zeros", align_corners=False)
                        term = term * prob.view(1, 1, t)
                    acc = acc.index_add(0, qi, term.view(self.c, t).t())
                out.append(acc / hit.sum(0).clamp(min=1).to(dt)[:, None])
            outputs.append(self.output_proj[p](torch.stack(out)))
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

    def forward(
        self, queries: list[torch.Tensor], pos: list[torch.Tensor], shape: tuple[int, int, int], ref: list[torch.Tensor]
    ) -> list[torch.Tensor]:
        """queries[p] (B, Q_p, C) for HW, ZH, WZ; ref[p] (Q_p, 3, A, 2): anchors of each query on each plane map."""
        h, w, z = shape
        b, ch = queries[0].shape[0], self.c // self.m
        maps = [(h, w), (z, h), (w, z)]  # (rows, cols) of the HW, ZH, WZ planes
        values = []
        for q, (rows, cols) in zip(queries, maps):
            v = self.value_proj(q).view(b, rows, cols, self.m, ch).permute(0, 3, 4, 1, 2)
            values.append(v.reshape(b * self.m, ch, rows, cols))
        norm = torch.tensor([[c, r] for r, c in maps], dtype=queries[0].dtype, device=queries[0].device).view(
            1, 1, 1, 3, 1, 1, 2
        )
        outputs = []
        for p, (q, qpos) in enumerate(zip(queries, pos)):
            nq, a = q.shape[1], ref[p].shape[2]
            x = q + qpos
            offsets = self.sampling_offsets[p](x).view(b, nq, self.m, 3, a, self.p // a, 2)
            weights = (
                self.attention_weights[p](x).view(b, nq, self.m, 3 * self.p).softmax(-1).view(b, nq, self.m, 3, self.p)
            )
            chunks = []
            for s in range(0, nq, self.query_chunk):
                e = min(nq, s + self.query_chunk)
                loc = ref[p][None, s:e, None, :, :, None, :] + offsets[:, s:e] / norm
                loc = loc.reshape(b, e - s, self.m, 3, self.p, 2)
                chunks.append(deformable_sample(values, loc, weights[:, s:e]))
            outputs.append(self.output_proj[p](torch.cat(chunks, 1)))
        return outputs
