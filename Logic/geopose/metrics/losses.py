"""Differentiable image similarity and the Dice loss (torch): the test-time optimisation
objective and the training losses.

Images are ``(B, C, H, W)`` tensors; values are per batch item ``(B,)`` (averaged over
channels). The same NCC family in numpy, for scoring, is :mod:`geopose.metrics.similarity`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..contract import MNCC_GLOBAL_WEIGHT, MNCC_PATCH_PX, NCC_EPS

__all__ = ["ncc_similarity", "local_ncc_similarity", "mncc_similarity", "generalized_dice_loss"]


def _check_pair(a: Tensor, b: Tensor) -> None:
    if a.ndim != 4 or a.shape != b.shape:
        raise ValueError(f"expected two (B, C, H, W) images of the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")


# ------------------------------------------------------------------ similarity
# NCC scale convention: images are compared on the scale of the networks' min-max
# inputs, i.e. each image channel is first shifted to zero mean and divided by its
# (max - min) range, so ``eps`` acts on a [0, 1]-range image whatever the input
# units (DSA grey values, DRR line integrals). This also keeps the pooled
# E[x^2] - E[x]^2 patch moments accurate in float32.


def _unit_range(x: Tensor) -> Tensor:
    """Zero mean and unit (max - min) range per image channel; a constant channel becomes 0."""
    x = x - x.mean(dim=(-2, -1), keepdim=True)
    span = x.amax(dim=(-2, -1), keepdim=True) - x.amin(dim=(-2, -1), keepdim=True)
    return torch.where(span > 0, x / torch.where(span > 0, span, torch.ones_like(span)), torch.zeros_like(x))


def ncc_similarity(a: Tensor, b: Tensor, eps: float = NCC_EPS) -> Tensor:
    """Global normalised cross-correlation ``(B,)`` in [-1, 1].

    Each image channel (unit range, see above) is z-scored, ``(x - mean) / sqrt(var + eps)``;
    the NCC is the mean product, averaged over channels.
    """
    _check_pair(a, b)
    a, b = _unit_range(a).flatten(2), _unit_range(b).flatten(2)
    za = (a - a.mean(-1, keepdim=True)) / torch.sqrt(a.var(-1, unbiased=False, keepdim=True) + eps)
    zb = (b - b.mean(-1, keepdim=True)) / torch.sqrt(b.var(-1, unbiased=False, keepdim=True) + eps)
    return (za * zb).mean(-1).mean(-1)


def local_ncc_similarity(a: Tensor, b: Tensor, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> Tensor:
    """Mean NCC ``(B,)`` over all ``patch_px`` x ``patch_px`` patches (stride 1, no padding).

    Each patch is z-scored like :func:`ncc_similarity`; local moments come from average pooling,
    and each patch value is clamped to [-1, 1] against float32 rounding.
    """
    _check_pair(a, b)
    if min(a.shape[-2:]) < patch_px:
        raise ValueError(f"images of {tuple(a.shape[-2:])} px are smaller than the {patch_px} px NCC patch")
    a, b = _unit_range(a), _unit_range(b)
    pool = lambda x: F.avg_pool2d(x, patch_px, stride=1)  # noqa: E731
    mu_a, mu_b = pool(a), pool(b)
    var_a = (pool(a * a) - mu_a * mu_a).clamp_min(0)
    var_b = (pool(b * b) - mu_b * mu_b).clamp_min(0)
    cov = pool(a * b) - mu_a * mu_b
    patch_ncc = (cov / torch.sqrt((var_a + eps) * (var_b + eps))).clamp(-1.0, 1.0)
    return patch_ncc.mean(dim=(-2, -1)).mean(-1)


def mncc_similarity(a: Tensor, b: Tensor, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> Tensor:
    """Multiscale NCC ``(B,)``: ``MNCC_GLOBAL_WEIGHT`` x global NCC + the rest x mean patch NCC."""
    return MNCC_GLOBAL_WEIGHT * ncc_similarity(a, b, eps) + (1.0 - MNCC_GLOBAL_WEIGHT) * local_ncc_similarity(a, b, patch_px, eps)


def generalized_dice_loss(pred: Tensor, target: Tensor, *, with_background: bool = True) -> Tensor:
    """Generalised Dice loss (Sudre et al. 2017) ``(B,)`` in [0, 1].

    ``pred`` holds soft foreground probabilities ``(B, C, H, W)`` in [0, 1], ``target``
    the reference masks of the same shape. Classes are the channels, plus their
    complements when ``with_background`` (the two-class form for binary masks).
    Class weights are ``1 / max(sum(target), 1)^2`` (target pixel counts).
    """
    _check_pair(pred, target)
    target = target.to(pred.dtype)
    if with_background:
        pred = torch.cat((pred, 1.0 - pred), dim=1)
        target = torch.cat((target, 1.0 - target), dim=1)
    p, g = pred.flatten(2), target.flatten(2)
    weights = 1.0 / g.sum(-1).clamp_min(1.0) ** 2
    overlap = (weights * (p * g).sum(-1)).sum(-1)
    total = (weights * (p + g).sum(-1)).sum(-1)
    dice = torch.where(total > 0, 2.0 * overlap / torch.where(total > 0, total, torch.ones_like(total)), torch.ones_like(total))
    return 1.0 - dice
