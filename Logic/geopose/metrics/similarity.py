"""The NCC family and the Dice loss in numpy (float64): scores of the refinement gate, the final mNCC,
the objective's numpy kernel and the benchmark.

Same definitions: each image is brought to zero mean and unit (max - min) range,
then z-scored globally (:func:`ncc`) or per ``patch_px`` patch (:func:`local_ncc`,
stride 1, no padding); :func:`mncc` mixes them with ``MNCC_GLOBAL_WEIGHT``.
Images are ``(H, W)``; the differentiable torch twins are in ``losses.py`` (tested equal).
"""

from __future__ import annotations

import numpy as np

from ..contract import MNCC_GLOBAL_WEIGHT, MNCC_PATCH_PX, NCC_EPS

__all__ = ["ncc", "local_ncc", "mncc", "generalized_dice_loss"]


def _check_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"expected two (H, W) images of the same shape, got {a.shape} and {b.shape}")
    return a, b


def _unit_range(x: np.ndarray) -> np.ndarray:
    x = x - x.mean()
    span = x.max() - x.min()
    return x / span if span > 0 else np.zeros_like(x)


def _box_mean(x: np.ndarray, patch_px: int) -> np.ndarray:
    """Mean over every ``patch_px`` x ``patch_px`` window (valid positions only)."""
    c = np.pad(x, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    p = patch_px
    return (c[p:, p:] - c[:-p, p:] - c[p:, :-p] + c[:-p, :-p]) / (p * p)


def ncc(a: np.ndarray, b: np.ndarray, eps: float = NCC_EPS) -> float:
    """Global normalised cross-correlation in [-1, 1]."""
    a, b = _check_pair(a, b)
    a, b = _unit_range(a), _unit_range(b)
    za = (a - a.mean()) / np.sqrt(a.var() + eps)
    zb = (b - b.mean()) / np.sqrt(b.var() + eps)
    return float((za * zb).mean())


def local_ncc(a: np.ndarray, b: np.ndarray, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> float:
    """Mean NCC over all ``patch_px`` x ``patch_px`` patches, each clamped to [-1, 1]."""
    a, b = _check_pair(a, b)
    if min(a.shape) < patch_px:
        raise ValueError(f"images of {a.shape} px are smaller than the {patch_px} px NCC patch")
    a, b = _unit_range(a), _unit_range(b)
    mu_a, mu_b = _box_mean(a, patch_px), _box_mean(b, patch_px)
    var_a = np.maximum(_box_mean(a * a, patch_px) - mu_a * mu_a, 0.0)
    var_b = np.maximum(_box_mean(b * b, patch_px) - mu_b * mu_b, 0.0)
    cov = _box_mean(a * b, patch_px) - mu_a * mu_b
    return float(np.clip(cov / np.sqrt((var_a + eps) * (var_b + eps)), -1.0, 1.0).mean())


def mncc(a: np.ndarray, b: np.ndarray, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> float:
    """Multiscale NCC: ``MNCC_GLOBAL_WEIGHT`` x global NCC + the rest x mean patch NCC."""
    return MNCC_GLOBAL_WEIGHT * ncc(a, b, eps) + (1.0 - MNCC_GLOBAL_WEIGHT) * local_ncc(a, b, patch_px, eps)


def generalized_dice_loss(pred: np.ndarray, target: np.ndarray) -> float:
    """Two-class generalised Dice loss of a soft mask ``pred`` in [0, 1] and a binary ``target``
    (the definition of ``losses.generalized_dice_loss``, foreground and background)."""
    p = np.stack((pred, 1.0 - pred)).reshape(2, -1).astype(np.float64)
    g = np.stack((target, 1.0 - target)).reshape(2, -1).astype(np.float64)
    w = 1.0 / np.maximum(g.sum(1), 1.0) ** 2
    total = (w * (p + g).sum(1)).sum()
    return 1.0 - (2.0 * (w * (p * g).sum(1)).sum() / total if total > 0 else 1.0)
