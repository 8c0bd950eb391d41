"""ResNet-style image backbone and FPN neck in plain torch.

The `paper` preset is ResNet-101-sized (bottleneck blocks 3-4-23-3, outputs 512/1024/2048 channels from stages
2-4, FPN to 256 channels over 4 levels). The published TPV-Former uses deformable convolutions (DCNv2) in the last two
stages and a caffe-style frozen-BN ImageNet initialisation; here they are plain 3x3 convolutions, trained from scratch.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from occvo_core.models.tpvformer.config import BackboneConfig


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.shortcut = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout
            else nn.Identity()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(y)) + self.shortcut(x))


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)  # DCNv2 in the published stages 3-4
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, cout, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(cout)
        self.shortcut = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout
            else nn.Identity()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        return F.relu(self.bn3(self.conv3(y)) + self.shortcut(x))


class ResNet(nn.Module):
    """Stem (stride 4) then four stages (strides 1, 2, 2, 2); returns the outputs of `out_stages`."""

    def __init__(self, cfg: BackboneConfig):
        super().__init__()
        block = Bottleneck if cfg.block == "bottleneck" else BasicBlock
        self.stem = nn.Sequential(
            nn.Conv2d(3, cfg.stem_channels, 7, 2, 3, bias=False),
            nn.BatchNorm2d(cfg.stem_channels),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        cin, stages = cfg.stem_channels, []
        for i, (n, width) in enumerate(zip(cfg.layers, cfg.widths)):
            blocks = []
            for j in range(n):
                blocks.append(block(cin, width, 2 if (j == 0 and i > 0) else 1))
                cin = width * block.expansion
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.ModuleList(stages)
        self.out_stages = tuple(cfg.out_stages)
        self.out_channels = [cfg.widths[i] * block.expansion for i in self.out_stages]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x, outs = self.stem(x), []
        for i, stage in enumerate(self.stages):
            x = stage(x)
            if i in self.out_stages:
                outs.append(x)
        return outs


class FPN(nn.Module):
    """Feature pyramid: lateral 1x1 + top-down sum + 3x3 output convs; extra stride-2 levels from the top output (ReLU first)."""

    def __init__(self, in_channels: list[int], out_channels: int, num_levels: int):
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in in_channels)
        self.output = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, 1, 1) for _ in in_channels)
        self.extra = nn.ModuleList(
            nn.Conv2d(out_channels, out_channels, 3, 2, 1) for _ in range(num_levels - len(in_channels))
        )

    def forward(self, feats: list[torch.Tensor]) -> list[torch.Tensor]:
        lat = [conv(f) for conv, f in zip(self.lateral, feats)]
        for i in range(len(lat) - 1, 0, -1):
            lat[i - 1] = lat[i - 1] + F.interpolate(lat[i], size=lat[i - 1].shape[-2:], mode="nearest")
        outs = [conv(x) for conv, x in zip(self.output, lat)]
        for conv in self.extra:
            outs.append(conv(F.relu(outs[-1])))
        return outs


class ImageBackbone(nn.Module):
    """Images (N,3,H,W) normalised -> list of FPN levels (N,C,H_l,W_l), finest first."""

    def __init__(self, cfg: BackboneConfig):
        super().__init__()
        self.resnet = ResNet(cfg)
        self.fpn = FPN(self.resnet.out_channels, cfg.fpn_channels, cfg.num_levels)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.fpn(self.resnet(x))
