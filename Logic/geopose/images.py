"""Image operations shared by DSA preprocessing, rendering and the networks (numpy; min-max also torch)."""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

import numpy as np

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["block_mean", "normalize_minmax", "resize_bilinear"]

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


def resize_bilinear(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(C, h, w)`` -> ``(C, H, W)`` float32, bilinear with pixel-centre alignment (torch's
    ``interpolate(mode="bilinear", align_corners=False)``)."""
    _, h, w = image.shape
    H, W = shape

    def axis(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.clip((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0, None)
        i0 = np.minimum(np.floor(x).astype(np.int64), n_in - 1)
        return i0, np.minimum(i0 + 1, n_in - 1), (x - i0).astype(np.float32)

    r0, r1, fr = axis(h, H)
    c0, c1, fc = axis(w, W)
    rows = image[:, r0] * (1 - fr)[:, None] + image[:, r1] * fr[:, None]
    return (rows[:, :, c0] * (1 - fc) + rows[:, :, c1] * fc).astype(np.float32)


def block_mean(array: np.ndarray, factors: tuple[int, ...]) -> np.ndarray:
    """Mean over blocks of ``factors`` (one per axis) of an array (edge blocks average what they hold), float32."""
    out = np.asarray(array, dtype=np.float32)
    for axis, f in enumerate(factors):
        if f == 1:
            continue
        n = out.shape[axis]
        pad = (-n) % f
        sums = np.add.reduceat(out, np.arange(0, n, f), axis=axis)
        counts = np.full(sums.shape[axis], f, dtype=np.float32)
        if pad:
            counts[-1] = f - pad
        shape = [1] * out.ndim
        shape[axis] = -1
        out = sums / counts.reshape(shape)
    return out
