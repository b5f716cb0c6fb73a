"""GeoPose-Init and GeoPose-Refine (docs/conventions.md section 4).

Both modules are rooted so that their ``state_dict`` keys equal the published
checkpoints' keys (``net.*``); only the Refine checkpoint's ``criterion.*``
entries (a training loss) have no counterpart.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor, nn

from ..contract import VIEW_EMBEDDING_DIM
from .decoding import NUM_VIEWS
from .resnet import BackboneConfig, ResNetEncoder

#: Hidden width of the Refine fusion layer of the published model.
REFINE_FUSION_DIM = 512
#: Features per image pair in the siamese Refine fusion: [a, b, a-b, |a-b|, a*b].
REFINE_PAIR_TERMS = 5
#: How Refine sees its image pair: ``siamese`` (the published layout: one encoder per image, features
#: fused) or ``stacked`` (ours: target and render as the two channels of one encoder, compared pixel by
#: pixel from the first layer on, at half the cost of two encoder passes).
REFINE_PAIRINGS = ("siamese", "stacked")
#: Outputs of both pose heads: 3 rotation + 3 translation parameters.
POSE_PARAMS = 6
MODEL_KINDS = ("init", "refine")


@dataclass(frozen=True)
class NetConfig:
    """Architecture of an Init or Refine network; enough to rebuild the module."""

    kind: str
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    embedding_dim: int = VIEW_EMBEDDING_DIM
    fusion_dim: int = REFINE_FUSION_DIM
    pairing: str = "siamese"

    def __post_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"network kind must be one of {MODEL_KINDS}, got {self.kind!r}")
        if self.pairing not in REFINE_PAIRINGS or (self.kind == "init" and self.pairing != "siamese"):
            raise ValueError(f"pairing must be one of {REFINE_PAIRINGS} ('stacked' for Refine only), got {self.pairing!r}")
        channels = 2 if self.pairing == "stacked" else 1
        if self.backbone.in_channels != channels:
            raise ValueError(f"a {self.pairing} {self.kind} network takes {channels}-channel images, but its backbone "
                             f"has {self.backbone.in_channels} input channels")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "NetConfig":
        values = dict(data)
        values["backbone"] = BackboneConfig(**values.get("backbone", {}))
        return cls(**values)


#: The published models' configurations (ResNet-34, width 64).
PUBLISHED_INIT_CONFIG = NetConfig("init")
PUBLISHED_REFINE_CONFIG = NetConfig("refine")


def _view_tensor(view: Tensor | int, batch: int, device: torch.device) -> Tensor:
    """View labels (0 LAT-, 1 PA, 2 LAT+) as int64 ``(batch,)`` on ``device``; an int is broadcast."""
    labels = torch.as_tensor(view, dtype=torch.int64, device=device)
    labels = labels.expand(batch) if labels.ndim == 0 else labels
    if labels.shape != (batch,) or bool(((labels < 0) | (labels >= NUM_VIEWS)).any()):
        raise ValueError(f"view labels must be in 0..{NUM_VIEWS - 1}, scalar or shape ({batch},), got {labels.tolist()}")
    return labels


def _check_images(name: str, image: Tensor) -> None:
    if image.ndim != 4 or image.shape[1] != 1:
        raise ValueError(f"{name} must be a (B, 1, H, W) image batch, got shape {tuple(image.shape)}")


class InitHead(nn.Module):
    """Init heads: view-conditioned pose regression, view logits and a (training-only) domain logit."""

    def __init__(self, feature_dim: int, embedding_dim: int) -> None:
        super().__init__()
        self.role_embedding = nn.Embedding(NUM_VIEWS, embedding_dim)
        self.pose = nn.Linear(feature_dim + embedding_dim, POSE_PARAMS)
        self.domain = nn.Linear(feature_dim, 1)
        self.view = nn.Linear(feature_dim, NUM_VIEWS)


class InitBody(ResNetEncoder):
    """The ResNet trunk with the Init heads in place of torchvision's ``fc``."""

    def __init__(self, config: NetConfig) -> None:
        super().__init__(config.backbone)
        self.fc = InitHead(config.backbone.feature_dim, config.embedding_dim)


class InitNet(nn.Module):
    """GeoPose-Init: one 1-channel image (min-max in [0, 1]) -> pose of the C-arm.

    ``forward(image, view)`` -> raw pose ``(B, 6)`` for the given view labels and
    view logits ``(B, 3)`` over (LAT-, PA, LAT+).
    """

    def __init__(self, config: NetConfig = PUBLISHED_INIT_CONFIG) -> None:
        super().__init__()
        if config.kind != "init":
            raise ValueError(f"InitNet needs an 'init' configuration, got {config.kind!r}")
        self.config = config
        self.net = InitBody(config)

    def _pose_raw(self, features: Tensor, view: Tensor) -> Tensor:
        embedding = self.net.fc.role_embedding(view)
        return self.net.fc.pose(torch.cat((features, embedding), dim=1))

    def forward(self, image: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        _check_images("image", image)
        features = self.net(image)
        view = _view_tensor(view, image.shape[0], image.device)
        return self._pose_raw(features, view), self.net.fc.view(features)

    def forward_all_views(self, image: Tensor) -> tuple[Tensor, Tensor]:
        """Raw pose for every view label ``(B, 3, 6)`` and view logits ``(B, 3)`` in one pass."""
        _check_images("image", image)
        features = self.net(image)
        batch = features.shape[0]
        labels = torch.arange(NUM_VIEWS, device=image.device).repeat(batch)
        raw = self._pose_raw(features.repeat_interleave(NUM_VIEWS, dim=0), labels)
        return raw.view(batch, NUM_VIEWS, POSE_PARAMS), self.net.fc.view(features)

    def domain_logit(self, image: Tensor) -> Tensor:
        """Training-only domain classifier logit ``(B, 1)``."""
        return self.net.fc.domain(self.net(image))


class RefineBody(nn.Module):
    """Encoder (siamese or stacked pair), fusion, view embedding and pose-residual head."""

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        features = config.backbone.feature_dim * (REFINE_PAIR_TERMS if config.pairing == "siamese" else 1)
        self.backbone = ResNetEncoder(config.backbone)
        self.fusion = nn.Sequential(nn.Linear(features, config.fusion_dim), nn.ReLU(inplace=True))
        self.view_emb = nn.Embedding(NUM_VIEWS, config.embedding_dim)
        self.head = nn.Linear(config.fusion_dim + config.embedding_dim, POSE_PARAMS)


class RefineNet(nn.Module):
    """GeoPose-Refine: (target, current render, view) -> raw residual ``(B, 6)``.

    Both images are ``(B, 1, H, W)`` min-max in [0, 1]. Siamese (published): the encoder is
    shared and runs on the two images separately (separate batch-norm statistics in training);
    stacked: it runs once on the two images as channels (target first).
    """

    def __init__(self, config: NetConfig = PUBLISHED_REFINE_CONFIG) -> None:
        super().__init__()
        if config.kind != "refine":
            raise ValueError(f"RefineNet needs a 'refine' configuration, got {config.kind!r}")
        self.config = config
        self.net = RefineBody(config)

    def forward(self, target: Tensor, render: Tensor, view: Tensor) -> Tensor:
        _check_images("target", target)
        _check_images("render", render)
        if target.shape != render.shape:
            raise ValueError(f"target {tuple(target.shape)} and render {tuple(render.shape)} must have the same shape")
        if self.config.pairing == "stacked":
            fused = self.net.fusion(self.net.backbone(torch.cat((target, render), dim=1)))
        else:
            a = self.net.backbone(target)
            b = self.net.backbone(render)
            fused = self.net.fusion(torch.cat((a, b, a - b, (a - b).abs(), a * b), dim=1))
        view = _view_tensor(view, target.shape[0], target.device)
        return self.net.head(torch.cat((fused, self.net.view_emb(view)), dim=1))


def build_model(config: NetConfig) -> InitNet | RefineNet:
    """A freshly initialised module for ``config``."""
    return InitNet(config) if config.kind == "init" else RefineNet(config)


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
