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

__all__ = ["ncc", "local_ncc", "mncc", "MNCCTarget", "generalized_dice_loss"]


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


def _global_terms(x: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """An image brought to zero mean and unit range, and that z-scored (the global NCC's term)."""
    x = _unit_range(x)
    return x, (x - x.mean()) / np.sqrt(x.var() + eps)


def _patch_terms(x: np.ndarray, patch_px: int, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per ``patch_px`` patch of a unit-range image: its mean and its variance plus ``eps``."""
    mu = _box_mean(x, patch_px)
    return mu, np.maximum(_box_mean(x * x, patch_px) - mu * mu, 0.0) + eps


def _patch_ncc(a: np.ndarray, mu_a: np.ndarray, var_a: np.ndarray, b: np.ndarray, mu_b: np.ndarray, var_b: np.ndarray,
               patch_px: int) -> float:
    cov = _box_mean(a * b, patch_px) - mu_a * mu_b
    return float(np.clip(cov / np.sqrt(var_a * var_b), -1.0, 1.0).mean())


def _check_patch(shape: tuple[int, ...], patch_px: int) -> None:
    if min(shape) < patch_px:
        raise ValueError(f"images of {shape} px are smaller than the {patch_px} px NCC patch")


def ncc(a: np.ndarray, b: np.ndarray, eps: float = NCC_EPS) -> float:
    """Global normalised cross-correlation in [-1, 1]."""
    a, b = _check_pair(a, b)
    return float((_global_terms(a, eps)[1] * _global_terms(b, eps)[1]).mean())


def local_ncc(a: np.ndarray, b: np.ndarray, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> float:
    """Mean NCC over all ``patch_px`` x ``patch_px`` patches, each clamped to [-1, 1]."""
    a, b = _check_pair(a, b)
    _check_patch(a.shape, patch_px)
    a, b = _unit_range(a), _unit_range(b)
    return _patch_ncc(a, *_patch_terms(a, patch_px, eps), b, *_patch_terms(b, patch_px, eps), patch_px)


def mncc(a: np.ndarray, b: np.ndarray, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> float:
    """Multiscale NCC: ``MNCC_GLOBAL_WEIGHT`` x global NCC + the rest x mean patch NCC."""
    return MNCCTarget(a, patch_px, eps)(b)


class MNCCTarget:
    """:func:`mncc` of one ``target`` ``(H, W)`` against many images (``score(image)``), the target's terms computed
    once: the same value as ``mncc(target, image)``, bit for bit."""

    def __init__(self, target: np.ndarray, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> None:
        target = np.asarray(target, dtype=np.float64)
        if target.ndim != 2:
            raise ValueError(f"expected an (H, W) image, got {target.shape}")
        _check_patch(target.shape, patch_px)
        self.shape, self.patch_px, self.eps = target.shape, patch_px, eps
        self._unit, self._z = _global_terms(target, eps)
        self._mu, self._var = _patch_terms(self._unit, patch_px, eps)

    def __call__(self, image: np.ndarray) -> float:
        """The mNCC of the target and ``image`` (same shape)."""
        image = np.asarray(image, dtype=np.float64)
        if image.shape != self.shape:
            raise ValueError(f"expected two (H, W) images of the same shape, got {self.shape} and {image.shape}")
        unit, z = _global_terms(image, self.eps)
        global_ncc = float((self._z * z).mean())
        local = _patch_ncc(self._unit, self._mu, self._var, unit, *_patch_terms(unit, self.patch_px, self.eps), self.patch_px)
        return MNCC_GLOBAL_WEIGHT * global_ncc + (1.0 - MNCC_GLOBAL_WEIGHT) * local


def generalized_dice_loss(pred: np.ndarray, target: np.ndarray) -> float:
    """Two-class generalised Dice loss of a soft mask ``pred`` in [0, 1] and a binary ``target``
    (the definition of ``losses.generalized_dice_loss``, foreground and background)."""
    p = np.stack((pred, 1.0 - pred)).reshape(2, -1).astype(np.float64)
    g = np.stack((target, 1.0 - target)).reshape(2, -1).astype(np.float64)
    w = 1.0 / np.maximum(g.sum(1), 1.0) ** 2
    total = (w * (p + g).sum(1)).sum()
    return 1.0 - (2.0 * (w * (p * g).sum(1)).sum() / total if total > 0 else 1.0)
