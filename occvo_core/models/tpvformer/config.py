"""One typed configuration for TPV-Former, with the `paper` and `tiny` presets."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from occvo_core.errors import ConfigError
from occvo_core.grid import NUM_CLASSES, OCC3D_GRID


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BackboneConfig(_Section):
    block: Literal["basic", "bottleneck"] = "bottleneck"
    layers: tuple[int, int, int, int] = (3, 4, 23, 3)  # ResNet-101
    stem_channels: int = Field(64, ge=4)
    widths: tuple[int, int, int, int] = (64, 128, 256, 512)  # bottleneck outputs are 4x these
    out_stages: tuple[int, ...] = (1, 2, 3)  # 0-based stages fed to the FPN
    fpn_channels: int = Field(256, ge=4)
    num_levels: int = Field(4, ge=1, description="FPN outputs: one per out stage, then stride-2 extra convs")


class TPVFormerConfig(_Section):
    input_size: tuple[int, int] = (1600, 900)  # width, height of each camera image this preset is trained for
    backbone: BackboneConfig = BackboneConfig()
    tpv_h: int = Field(200, ge=1, description="plane size along ego x")
    tpv_w: int = Field(200, ge=1, description="plane size along ego y")
    tpv_z: int = Field(16, ge=1, description="plane size along ego z")
    embed_dims: int = Field(256, ge=8)
    num_heads: int = Field(8, ge=1)
    ffn_dims: int = Field(512, ge=8)
    num_layers: int = Field(3, ge=1)
    dropout: float = Field(0.1, ge=0, lt=1)
    points_in_pillar: tuple[int, int, int] = (4, 32, 32)  # 3D anchors per query of the HW, ZH, WZ planes
    sampling_points: tuple[int, int, int] = (8, 64, 64)  # image sampling points per head and level, per plane
    visible_anchors_only: bool = Field(
        False,
        description="image cross attention samples around only the anchors that land in "
        "a camera's image (the published model: all anchors of a query the camera sees)",
    )
    depth_bins: int = Field(
        0,
        ge=0,
        description="depth-aware image cross attention: a depth head on the finest FPN level "
        "predicts this many log-spaced bins over depth_range; 0 = off (the published model)",
    )
    depth_range: tuple[float, float] = (1.0, 80.0)
    hybrid_anchors: int = Field(4, ge=1, description="anchors on each other plane for cross-view hybrid attention")
    hybrid_points: int = Field(4, ge=1, description="sampling points per head per plane in cross-view hybrid attention")
    decoder_hidden: int = Field(512, ge=8)
    decoder_out: int = Field(256, ge=8)
    decoder_activation: Literal["softplus", "relu"] = Field(
        "softplus", description="relu: a third of softplus's cost on CPU"
    )
    decode_shape: tuple[int, int, int] | None = Field(
        None,
        description="run the voxel MLP here, then upsample the logits "
        "trilinearly to the grid; None = at the grid resolution",
    )
    plane_upsampling: Literal["bilinear", "deconv"] = Field(
        "bilinear",
        description="planes to decode_shape: bilinear "
        "(then the decoder's first layer), or a learned transposed "
        "convolution per plane giving each sub-cell its own features",
    )
    num_classes: int = NUM_CLASSES
    free_logit_bias: float = Field(
        0.0,
        description="added to the free-class logit at inference: undoes the class "
        "weighting's push towards occupied; calibrated on training scenes after training",
    )
    lift_range: float = Field(
        0.0,
        ge=0,
        description="depth lifting at inference: occupied = the voxels that pixels land in at the depth head's "
        "most likely depth, within this many metres (horizontally), each with the decoder's best occupied class; "
        "the rest free. 0 = off (the decoder's argmax)",
    )
    label_prior: bool = Field(
        False,
        description="a learned per-voxel offset of the free logit at decode_shape (the grid if None), initialised "
        "from the training labels' ego-frame occupancy frequency (occvo train-occ --label-prior)",
    )
    lift_upsample: int = Field(4, ge=1, description="the depth distribution upsampled this many times before lifting")
    grid_shape: tuple[int, int, int] = OCC3D_GRID.shape
    lower: tuple[float, float, float] = OCC3D_GRID.lower
    upper: tuple[float, float, float] = OCC3D_GRID.upper
    query_chunk: int = Field(16384, ge=64, description="queries sampled at once: bounds peak memory")
    decoder_chunk: int = Field(25, ge=1, description="x-slices of the voxel grid decoded at once")

    @model_validator(mode="after")
    def _check(self) -> TPVFormerConfig:
        for name, size, full in (
            ("tpv_h", self.tpv_h, self.grid_shape[0]),
            ("tpv_w", self.tpv_w, self.grid_shape[1]),
            ("tpv_z", self.tpv_z, self.grid_shape[2]),
        ):
            if size > full:
                raise ValueError(f"{name}={size} is finer than the grid ({full})")
        if self.embed_dims % self.num_heads:
            raise ValueError(f"embed_dims {self.embed_dims} not divisible by num_heads {self.num_heads}")
        for a, p in zip(self.points_in_pillar, self.sampling_points):
            if p % a:
                raise ValueError(
                    f"sampling_points {self.sampling_points} must be multiples of points_in_pillar {self.points_in_pillar}"
                )
        if self.hybrid_points % self.hybrid_anchors:
            raise ValueError("hybrid_points must be a multiple of hybrid_anchors")
        if self.plane_upsampling == "deconv":
            if self.decode_shape is None:
                raise ValueError("plane_upsampling 'deconv' needs a decode_shape")
            for name, size, target in zip(
                ("tpv_h", "tpv_w", "tpv_z"), (self.tpv_h, self.tpv_w, self.tpv_z), self.decode_shape
            ):
                f = target // size
                if target % size or (f > 1 and f % 2):
                    raise ValueError(
                        f"plane_upsampling 'deconv': decode_shape {self.decode_shape} must be 1x or an even "
                        f"multiple of {name}={size}"
                    )
        if self.lift_range and not self.depth_bins:
            raise ValueError("lift_range needs a depth head (depth_bins > 0)")
        if self.backbone.num_levels < len(self.backbone.out_stages):
            raise ValueError("num_levels must be at least the number of out stages")
        return self


PRESETS: dict[str, TPVFormerConfig] = {
    # The published sizes (ResNet-101 + FPN, 4 levels, 256 dims, 3 layers) with TPV planes at the full 200x200x16 grid.
    "paper": TPVFormerConfig(),
    # Trainable on 2 CPU cores in minutes: 1/8-resolution images, a small ResNet, planes 50x50x8 upsampled to the grid
    # (learned, to 100x100x16, then trilinear). Departures from the published model, for CPU time and sample
    # efficiency: cross attention samples only anchors inside an image and weighs them by a predicted depth
    # distribution (depth supervised in training by the renderer), ReLU decoder.
    "tiny": TPVFormerConfig(
        input_size=(200, 112),
        backbone=BackboneConfig(
            block="basic",
            layers=(1, 1, 1, 1),
            stem_channels=16,
            widths=(16, 32, 48, 64),
            out_stages=(1, 2, 3),
            fpn_channels=48,
            num_levels=3,
        ),
        tpv_h=50,
        tpv_w=50,
        tpv_z=8,
        embed_dims=48,
        num_heads=4,
        ffn_dims=96,
        num_layers=2,
        dropout=0.0,
        points_in_pillar=(4, 8, 8),
        sampling_points=(4, 8, 8),
        visible_anchors_only=True,
        depth_bins=32,
        hybrid_anchors=2,
        hybrid_points=2,
        decoder_hidden=32,
        decoder_out=32,
        decoder_activation="relu",
        decode_shape=(100, 100, 16),
        plane_upsampling="deconv",
        decoder_chunk=100,
    ),
    # Between the two, for a GPU (benchmarks/gpu_check.sh trains it): quarter-resolution images, a ResNet-18-deep
    # backbone, planes at half the grid (learned upsampling to it), three layers; tiny's departures kept.
    "small": TPVFormerConfig(
        input_size=(400, 224),
        backbone=BackboneConfig(
            block="basic",
            layers=(2, 2, 2, 2),
            stem_channels=32,
            widths=(32, 64, 96, 128),
            out_stages=(1, 2, 3),
            fpn_channels=96,
            num_levels=3,
        ),
        tpv_h=100,
        tpv_w=100,
        tpv_z=8,
        embed_dims=96,
        num_heads=4,
        ffn_dims=192,
        num_layers=3,
        dropout=0.0,
        points_in_pillar=(4, 8, 8),
        sampling_points=(8, 16, 16),
        visible_anchors_only=True,
        depth_bins=48,
        hybrid_anchors=2,
        hybrid_points=4,
        decoder_hidden=48,
        decoder_out=48,
        decoder_activation="relu",
        decode_shape=(200, 200, 16),
        plane_upsampling="deconv",
        decoder_chunk=50,
    ),
}


def preset(name: str, **overrides) -> TPVFormerConfig:
    """A named preset, optionally with top-level fields replaced (validated again)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown TPV-Former preset {name!r}; choose one of {sorted(PRESETS)}")
    try:
        return TPVFormerConfig.model_validate({**PRESETS[name].model_dump(), **overrides})
    except Exception as exc:  # noqa: BLE001 - one clear error for a bad override
        raise ConfigError(f"preset {name!r} with {overrides}: {exc}") from None
