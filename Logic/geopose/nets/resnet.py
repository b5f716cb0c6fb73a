"""A torchvision-layout ResNet encoder (basic blocks) for 1-channel images.

Parameter names follow torchvision (``conv1``, ``bn1``, ``layer1.0.conv1``, ...,
``downsample.0/1``) so that the published GeoPose state dicts load strictly.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

#: Basic blocks per stage for the supported depths.
BLOCKS_PER_STAGE: dict[int, tuple[int, int, int, int]] = {18: (2, 2, 2, 2), 34: (3, 4, 6, 3)}
#: torchvision's stem width; stage widths are (1, 2, 4, 8) x the base width.
STANDARD_BASE_WIDTH = 64
STAGE_WIDTH_FACTORS = (1, 2, 4, 8)


@dataclass(frozen=True)
class BackboneConfig:
    """ResNet depth (18 or 34), stem width (channels of ``conv1``) and input channels."""

    depth: int = 34
    base_width: int = STANDARD_BASE_WIDTH
    in_channels: int = 1

    def __post_init__(self) -> None:
        if self.depth not in BLOCKS_PER_STAGE:
            raise ValueError(f"ResNet depth {self.depth} is not supported; use one of {sorted(BLOCKS_PER_STAGE)}")
        if self.base_width < 1 or self.in_channels < 1:
            raise ValueError(f"base_width and in_channels must be positive, got {self.base_width}, {self.in_channels}")

    @property
    def feature_dim(self) -> int:
        """Length of the pooled feature vector."""
        return self.base_width * STAGE_WIDTH_FACTORS[-1]

    def to_dict(self) -> dict:
        return asdict(self)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with a residual connection (1x1 projection when the shape changes)."""

    def __init__(self, in_planes: int, planes: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_planes != planes:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_planes, planes, 1, stride=stride, bias=False), nn.BatchNorm2d(planes)
            )

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNetEncoder(nn.Module):
    """ResNet-18/34 trunk: image ``(B, C, H, W)`` -> pooled features ``(B, feature_dim)``."""

    def __init__(self, config: BackboneConfig) -> None:
        super().__init__()
        self.config = config
        width = config.base_width
        self.conv1 = nn.Conv2d(config.in_channels, width, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        in_planes = width
        for index, (blocks, factor) in enumerate(zip(BLOCKS_PER_STAGE[config.depth], STAGE_WIDTH_FACTORS)):
            planes = width * factor
            stride = 1 if index == 0 else 2
            stage = [BasicBlock(in_planes, planes, stride)]
            stage += [BasicBlock(planes, planes, 1) for _ in range(blocks - 1)]
            setattr(self, f"layer{index + 1}", nn.Sequential(*stage))
            in_planes = planes
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return torch.flatten(self.avgpool(x), 1)
