"""The one image normalisation every network input goes through (numpy or torch)."""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

import numpy as np

if TYPE_CHECKING:
    from torch import Tensor

ImageBatch = TypeVar("ImageBatch", np.ndarray, "Tensor")


def normalize_minmax(image: ImageBatch) -> ImageBatch:
    """Per-image min-max scaling to [0, 1] of a ``(B, C, H, W)`` batch (each item over C, H, W).

    Takes a numpy array (answers float32) or a torch tensor (answers a float tensor on
    its device). A constant image maps to all zeros. Returns a new array; the input
    is not altered. Idempotent: an image already spanning [0, 1] is returned unchanged.
    """
    if image.ndim != 4:
        raise ValueError(f"normalize_minmax expects a (B, C, H, W) batch, got shape {tuple(image.shape)}")
    if isinstance(image, np.ndarray):
        x = image.astype(np.float32, copy=False)
        flat = x.reshape(len(x), -1)
        low = flat.min(axis=1).reshape(-1, 1, 1, 1)
        span = flat.max(axis=1).reshape(-1, 1, 1, 1) - low
        return np.where(span > 0, (x - low) / np.where(span > 0, span, 1.0), 0.0).astype(np.float32)
    import torch

    x = image if torch.is_floating_point(image) else image.float()
    flat = x.flatten(1)
    low = flat.amin(dim=1).view(-1, 1, 1, 1)
    span = flat.amax(dim=1).view(-1, 1, 1, 1) - low
    scaled = (x - low) / torch.where(span > 0, span, torch.ones_like(span))
    return torch.where(span > 0, scaled, torch.zeros_like(x))
