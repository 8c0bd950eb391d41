"""TPV-Former: six surround images -> tri-perspective view (HW, ZH, WZ planes) -> 18-class logits on the 200x200x16 grid.

Plane axes: H along ego x, W along ego y, Z along ego z. HW is the top view (rows x, columns y), ZH the side view
(rows z, columns x), WZ the front view (rows y, columns z). A voxel's feature is the sum of its three projections.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from occvo_core.grid import FREE
from occvo_core.models.tpvformer.attention import CrossViewHybridAttention, ImageCrossAttention
from occvo_core.models.tpvformer.backbone import ImageBackbone
from occvo_core.models.tpvformer.config import TPVFormerConfig
from occvo_core.models.tpvformer.lifting import lifted_points, lifted_voxels

IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)


def _centres(n: int) -> torch.Tensor:
    return (torch.arange(n, dtype=torch.float32) + 0.5) / n


class LearnedPositionalEncoding(nn.Module):
    """Row and column embeddings of a plane, concatenated (C/2 each), flattened row-major."""

    def __init__(self, dims: int, rows: int, cols: int):
        super().__init__()
        self.row = nn.Embedding(rows, dims // 2)
        self.col = nn.Embedding(cols, dims - dims // 2)

    def forward(self) -> torch.Tensor:
        r, c = self.row.weight, self.col.weight
        return torch.cat([r[:, None].expand(-1, len(c), -1), c[None].expand(len(r), -1, -1)], -1).flatten(0, 1)


def _upsampler(cin: int, cout: int, factors: tuple[int, int]) -> nn.Module:
    """Transposed convolution upsampling a plane by integer factors (1 or even): kernel 2f, stride f, padding f/2,
    so each output cell mixes its own and the neighbouring input cells (like bilinear, but learned)."""
    kernel = tuple(2 * f if f > 1 else 1 for f in factors)
    return nn.ConvTranspose2d(cin, cout, kernel, stride=factors, padding=tuple(f // 2 if f > 1 else 0 for f in factors))


class EncoderLayer(nn.Module):
    """Cross-view hybrid attention -> norm -> image cross attention -> norm -> FFN -> norm (each with a residual)."""

    def __init__(self, cfg: TPVFormerConfig):
        super().__init__()
        c = cfg.embed_dims
        self.hybrid = CrossViewHybridAttention(c, cfg.num_heads, cfg.hybrid_points, cfg.query_chunk)
        self.cross = ImageCrossAttention(
            c,
            cfg.num_heads,
            cfg.backbone.num_levels,
            cfg.points_in_pillar,
            cfg.sampling_points,
            cfg.query_chunk,
            cfg.visible_anchors_only,
            tuple(cfg.depth_range),
        )
        self.norms = nn.ModuleList(nn.LayerNorm(c) for _ in range(3))
        self.ffn = nn.Sequential(
            nn.Linear(c, cfg.ffn_dims), nn.ReLU(inplace=True), nn.Dropout(cfg.dropout), nn.Linear(cfg.ffn_dims, c)
        )
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, tpv, pos, shape, hybrid_ref, feats, ref_uv, ref_valid, ref_depth=None, depth_prob=None):
        tpv = [self.norms[0](t + self.drop(a)) for t, a in zip(tpv, self.hybrid(tpv, pos, shape, hybrid_ref))]
        cross = self.cross(tpv, pos, feats, ref_uv, ref_valid, ref_depth, depth_prob)
        tpv = [self.norms[1](t + self.drop(a)) for t, a in zip(tpv, cross)]
        return [self.norms[2](t + self.drop(self.ffn(t))) for t in tpv]


class TPVFormer(nn.Module):
    def __init__(self, cfg: TPVFormerConfig):
        super().__init__()
        self.cfg = cfg
        c, h, w, z = cfg.embed_dims, cfg.tpv_h, cfg.tpv_w, cfg.tpv_z
        self.backbone = ImageBackbone(cfg.backbone)
        fpn = cfg.backbone.fpn_channels
        self.input_proj = nn.Identity() if fpn == c else nn.Conv2d(fpn, c, 1)  # FPN width -> embed dims
        self.level_embed = nn.Parameter(torch.randn(cfg.backbone.num_levels, c) * 0.02)
        self.cams_embed = nn.Parameter(torch.randn(6, c) * 0.02)
        self.queries = nn.ParameterDict(
            {
                "hw": nn.Parameter(torch.randn(h * w, c) * 0.02),
                "zh": nn.Parameter(torch.randn(z * h, c) * 0.02),
                "wz": nn.Parameter(torch.randn(w * z, c) * 0.02),
            }
        )
        self.pos = nn.ModuleList(
            [LearnedPositionalEncoding(c, h, w), LearnedPositionalEncoding(c, z, h), LearnedPositionalEncoding(c, w, z)]
        )
        self.layers = nn.ModuleList(EncoderLayer(cfg) for _ in range(cfg.num_layers))
        fpn_c = cfg.backbone.fpn_channels
        self.depth_head = (
            nn.Sequential(
                nn.Conv2d(fpn_c, fpn_c, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(fpn_c, cfg.depth_bins, 1)
            )
            if cfg.depth_bins
            else None
        )
        act = nn.Softplus if cfg.decoder_activation == "softplus" else lambda: nn.ReLU(inplace=True)
        self.decoder = nn.Sequential(
            nn.Linear(c, cfg.decoder_hidden),
            act(),
            nn.Linear(cfg.decoder_hidden, cfg.decoder_out),
            act(),
            nn.Linear(cfg.decoder_out, cfg.num_classes),
        )
        self.plane_up = None
        if (
            cfg.plane_upsampling == "deconv"
        ):  # learned upsampling replaces the bilinear one and the decoder's first layer
            self.decoder[0] = nn.Identity()
            shapes = [(h, w), (z, h), (w, z)]
            gx, gy, gz = cfg.decode_shape
            targets = [(gx, gy), (gz, gx), (gy, gz)]
            self.plane_up = nn.ModuleList(
                _upsampler(c, cfg.decoder_hidden, tuple(t // n for t, n in zip(tg, sh)))
                for sh, tg in zip(shapes, targets)
            )
        if cfg.label_prior:  # where the training drive's labels were occupied, relative to the car (label_prior.py)
            self.free_prior = nn.Parameter(torch.zeros(tuple(cfg.decode_shape or cfg.grid_shape)))
        nn.init.normal_(self.decoder[-1].weight, std=0.01)  # start near uniform class scores: a calm first loss
        nn.init.zeros_(self.decoder[-1].bias)
        self.register_buffer("image_mean", torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("image_std", torch.tensor(IMAGE_STD).view(1, 3, 1, 1), persistent=False)
        for i, t in enumerate(self._pillar_anchors()):
            self.register_buffer(f"anchors_{i}", t, persistent=False)
        for i, t in enumerate(self._hybrid_reference()):
            self.register_buffer(f"hybrid_ref_{i}", t, persistent=False)

    # -- reference points ------------------------------------------------------------------------------------------
    def _pillar_anchors(self) -> list[torch.Tensor]:
        """3D anchors (Q_p, D_p, 3) in the ego frame: each plane cell's pillar along the plane's missing axis."""
        cfg = self.cfg
        lo, hi = torch.tensor(cfg.lower), torch.tensor(cfg.upper)
        xs, ys, zs = (lo[i] + (hi[i] - lo[i]) * _centres(n) for i, n in enumerate((cfg.tpv_h, cfg.tpv_w, cfg.tpv_z)))
        d_hw, d_zh, d_wz = cfg.points_in_pillar
        za, ya, xa = (lo[i] + (hi[i] - lo[i]) * _centres(n) for i, n in ((2, d_hw), (1, d_zh), (0, d_wz)))
        hw = torch.stack(torch.meshgrid(xs, ys, za, indexing="ij"), -1).flatten(0, 1)  # rows x, cols y, anchors z
        zh = torch.stack(torch.meshgrid(zs, xs, ya, indexing="ij"), -1).flatten(0, 1)[
            ..., [1, 2, 0]
        ]  # (z, x, y) -> xyz
        wz = torch.stack(torch.meshgrid(ys, zs, xa, indexing="ij"), -1).flatten(0, 1)[
            ..., [2, 0, 1]
        ]  # (y, z, x) -> xyz
        return [hw, zh, wz]

    def _hybrid_reference(self) -> list[torch.Tensor]:
        """Per plane (Q_p, 3, A, 2): (column, row) in [0, 1] on the HW, ZH, WZ maps for each query's anchors."""
        cfg, a = self.cfg, self.cfg.hybrid_anchors
        x, y, z, t = _centres(cfg.tpv_h), _centres(cfg.tpv_w), _centres(cfg.tpv_z), _centres(a)

        def pair(col, row):  # broadcast to (Q, A, 2) over the query grid given as leading dims
            col, row = torch.broadcast_tensors(col, row)
            return torch.stack([col, row], -1)

        # HW query (i, j): own cell; ZH map at column x_i, rows along z; WZ map at row y_j, columns along z.
        X, Y, T = torch.meshgrid(x, y, t, indexing="ij")
        hw = torch.stack([pair(Y, X), pair(X, T), pair(T, Y)], 2).flatten(0, 1)
        # ZH query (k, i): HW map row x_i, columns along y; own cell; WZ map column z_k, rows along y.
        Z, X, T = torch.meshgrid(z, x, t, indexing="ij")
        zh = torch.stack([pair(T, X), pair(X, Z), pair(Z, T)], 2).flatten(0, 1)
        # WZ query (j, k): HW map column y_j, rows along x; ZH map row z_k, columns along x; own cell.
        Y, Z, T = torch.meshgrid(y, z, t, indexing="ij")
        wz = torch.stack([pair(Y, T), pair(T, Z), pair(Z, Y)], 2).flatten(0, 1)
        return [hw, zh, wz]

    def project_anchors(
        self, intrinsics: torch.Tensor, cam_to_ego: torch.Tensor, image_hw: tuple[int, int], return_depth: bool = False
    ):
        """Anchors -> per plane normalised pixel coordinates (B, Ncam, Q, D, 2) and validity (in front, in image);
        with `return_depth` also their depths along each camera's optical axis (B, Ncam, Q, D)."""
        ego_to_pix = intrinsics @ torch.linalg.inv(cam_to_ego)[..., :3, :]  # (B, Ncam, 3, 4)
        ih, iw = image_hw
        uvs, valid, depths = [], [], []
        for i in range(3):
            pts = getattr(self, f"anchors_{i}")
            cam = torch.einsum("bnij,qdj->bnqdi", ego_to_pix[..., :3], pts) + ego_to_pix[..., 3][:, :, None, None, :]
            depth = cam[..., 2:3]
            uv = cam[..., :2] / depth.clamp(min=1e-5)
            uv = (uv + 0.5) / torch.tensor([iw, ih], dtype=uv.dtype, device=uv.device)  # pixel centres -> [0, 1] edges
            ok = (depth[..., 0] > 0.1) & (uv >= 0).all(-1) & (uv <= 1).all(-1)
            uvs.append(uv)
            valid.append(ok)
            depths.append(depth[..., 0])
        return (uvs, valid, depths) if return_depth else (uvs, valid)

    # -- forward ---------------------------------------------------------------------------------------------------
    def encode(self, images: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego: torch.Tensor) -> list[torch.Tensor]:
        """Images (B, 6, 3, H, W) in [0, 1] -> TPV planes [(B, C, H, W), (B, C, Z, H), (B, C, W, Z)]."""
        return self.encode_with_depth(images, intrinsics, cam_to_ego)[0]

    def image_depth(self, images: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The image branch alone: images (B, Ncam, 3, H, W) -> FPN levels (B*Ncam, C, h_l, w_l) and the depth head's
        logits (B*Ncam, bins, h, w) (None without a depth head)."""
        levels = self.backbone((images.flatten(0, 1) - self.image_mean) / self.image_std)
        return levels, (self.depth_head(levels[0]) if self.depth_head is not None else None)

    def encode_with_depth(
        self, images: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego: torch.Tensor
    ) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The TPV planes and the depth head's distribution (B, Ncam, bins, h, w) (None without a depth head)."""
        if images.dim() != 5 or images.shape[2] != 3:
            raise ValueError(f"images must be (B, Ncam, 3, H, W), got {tuple(images.shape)}")
        b, ncam, _, ih, iw = images.shape
        if intrinsics.shape != (b, ncam, 3, 3) or cam_to_ego.shape != (b, ncam, 4, 4):
            raise ValueError(
                f"intrinsics {tuple(intrinsics.shape)} / cam_to_ego {tuple(cam_to_ego.shape)} do not match "
                f"{ncam} cameras in a batch of {b}"
            )
        if ncam > self.cams_embed.shape[0]:
            raise ValueError(f"{ncam} cameras given, the model has embeddings for {self.cams_embed.shape[0]}")
        levels, depth_prob = self.image_depth(images)
        if depth_prob is not None:  # depth distribution of every pixel of the finest level
            depth_prob = depth_prob.softmax(1).view(b, ncam, -1, *depth_prob.shape[-2:])
        feats = [
            f.view(b, ncam, *f.shape[1:])
            + self.cams_embed[None, :ncam, :, None, None]
            + self.level_embed[lv, :, None, None]
            for lv, f in enumerate(map(self.input_proj, levels))
        ]
        ref_uv, ref_valid, ref_depth = self.project_anchors(
            intrinsics.float(), cam_to_ego.float(), (ih, iw), return_depth=True
        )
        if depth_prob is None:
            ref_depth = None
        cfg = self.cfg
        shape = (cfg.tpv_h, cfg.tpv_w, cfg.tpv_z)
        tpv = [self.queries[k][None].expand(b, -1, -1) for k in ("hw", "zh", "wz")]
        pos = [p()[None].expand(b, -1, -1) for p in self.pos]
        hybrid_ref = [getattr(self, f"hybrid_ref_{i}") for i in range(3)]
        for layer in self.layers:
            tpv = layer(tpv, pos, shape, hybrid_ref, feats, ref_uv, ref_valid, ref_depth, depth_prob)
        maps = [(cfg.tpv_h, cfg.tpv_w), (cfg.tpv_z, cfg.tpv_h), (cfg.tpv_w, cfg.tpv_z)]
        return [t.transpose(1, 2).reshape(b, -1, r, c) for t, (r, c) in zip(tpv, maps)], depth_prob

    def upsample(self, planes: list[torch.Tensor]) -> list[torch.Tensor]:
        """Planes to the decoding resolution; bilinear on each plane = trilinear on the broadcast volume."""
        gx, gy, gz = self.cfg.decode_shape or self.cfg.grid_shape
        sizes = [(gx, gy), (gz, gx), (gy, gz)]
        return [
            p if tuple(p.shape[-2:]) == s else F.interpolate(p, size=s, mode="bilinear", align_corners=False)
            for p, s in zip(planes, sizes)
        ]

    def decode(self, planes: list[torch.Tensor]) -> torch.Tensor:
        """Broadcast and sum the planes -> MLP -> logits (B, classes, X, Y, Z) on the grid.

        With a coarser `decode_shape` the MLP runs there and its logits are upsampled trilinearly to the grid.
        The MLP's first layer is linear, so it is applied to each plane before the broadcast (same result, far fewer
        multiplications than on every voxel).
        """
        first, rest = self.decoder[0], self.decoder[1:]
        if self.plane_up is not None:
            hw, zh, wz = (up(p).permute(0, 2, 3, 1) for up, p in zip(self.plane_up, planes))  # channels last
        else:
            # The first layer is linear and so is the bilinear upsampling: apply the layer at plane resolution first
            # (fewer pixels), then upsample its output in channels-last memory (the fast layout for interpolate on CPU).
            hidden = [F.linear(p.permute(0, 2, 3, 1), first.weight).permute(0, 3, 1, 2) for p in planes]
            hw, zh, wz = (p.permute(0, 2, 3, 1) for p in self.upsample(hidden))  # channels last
            hw = hw + first.bias
        gx = hw.shape[1]
        chunks = []
        for s in range(0, gx, self.cfg.decoder_chunk):
            e = min(gx, s + self.cfg.decoder_chunk)
            f = hw[:, s:e, :, None] + zh[:, :, s:e].transpose(1, 2)[:, :, None]  # (B, x, Y, Z, hidden)
            f += wz[:, None]  # in place: one pass less over the largest tensor of the decoder
            chunks.append(rest(f))
        logits = chunks[0] if len(chunks) == 1 else torch.cat(chunks, 1)  # (B, X, Y, Z, classes), classes innermost
        if self.cfg.label_prior:
            logits[..., FREE] += self.free_prior  # in place, as the offset below
        if self.cfg.free_logit_bias:
            logits[..., FREE] += self.cfg.free_logit_bias  # in place on the fresh logits: no second full tensor
        b, x, y, z, c = logits.shape
        gx, gy, gz = self.cfg.grid_shape
        if (x, y) != (gx, gy):
            if z != gz:
                logits = F.interpolate(
                    logits.permute(0, 4, 1, 2, 3), size=(gx, gy, gz), mode="trilinear", align_corners=False
                ).permute(0, 2, 3, 4, 1)
            else:  # z already at grid resolution: trilinear = bilinear over (x, y), done channels-last
                flat = logits.reshape(b, x, y, z * c).permute(0, 3, 1, 2)
                flat = F.interpolate(flat, size=(gx, gy), mode="bilinear", align_corners=False)
                logits = flat.permute(0, 2, 3, 1).reshape(b, gx, gy, z, c)
        return logits.permute(0, 4, 1, 2, 3)

    def forward(self, images: torch.Tensor, intrinsics: torch.Tensor, cam_to_ego: torch.Tensor) -> torch.Tensor:
        """images (B, 6, 3, H, W) in [0, 1], intrinsics (B, 6, 3, 3) for that image size, cam_to_ego (B, 6, 4, 4)
        -> logits (B, 18, 200, 200, 16). In eval mode with `lift_range`, the free logit decides by depth lifting."""
        planes, depth_prob = self.encode_with_depth(images, intrinsics, cam_to_ego)
        logits = self.decode(planes)
        if self.cfg.lift_range and not self.training:
            self.lift(logits, depth_prob, intrinsics, cam_to_ego, tuple(images.shape[-2:]))
        return logits

    def lift(self, logits, depth_prob, intrinsics, cam_to_ego, image_hw) -> None:
        """In place: the free logit far above every class outside the lifted voxels, far below inside them."""
        cfg = self.cfg
        for b in range(logits.shape[0]):
            points = lifted_points(
                depth_prob[b], intrinsics[b], cam_to_ego[b], image_hw, tuple(cfg.depth_range), cfg.lift_upsample
            )
            hit = lifted_voxels(points, tuple(cfg.lower), tuple(cfg.upper), tuple(cfg.grid_shape), cfg.lift_range)
            logits[b, FREE] = torch.where(hit, -1e4, 1e4).to(logits.dtype)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
