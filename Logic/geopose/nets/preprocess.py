"""The one image normalisation every network input goes through."""

from __future__ import annotations

import torch
from torch import Tensor


def normalize_minmax(image: Tensor) -> Tensor:
    """Per-image min-max scaling to [0, 1] of a ``(B, C, H, W)`` batch (each item over C, H, W).

    A constant image maps to all zeros. Returns a new tensor; the input is not altered.
    Idempotent: an image already spanning [0, 1] is returned unchanged.
    """
    if image.ndim != 4:
        raise ValueError(f"normalize_minmax expects a (B, C, H, W) batch, got shape {tuple(image.shape)}")
    if not torch.is_floating_point(image):
        image = image.float()
    flat = image.flatten(1)
    low = flat.amin(dim=1).view(-1, 1, 1, 1)
    span = flat.amax(dim=1).view(-1, 1, 1, 1) - low
    scaled = (image - low) / torch.where(span > 0, span, torch.ones_like(span))
    return torch.where(span > 0, scaled, torch.zeros_like(image))
