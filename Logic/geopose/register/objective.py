"""The GeoReg registration objective, as a score (numpy; no gradients).

Per view: ``w * (-mNCC(target, image)) + (1 - w) * GeneralizedDice(sigmoid(cranium
channel), DSA mask)`` in the acquisition geometry, ``image`` the DRR clipped like the
target (:class:`Objective`). The same objective, differentiable, is what the test-time
optimisation minimises (``tto.py``); scores here decide between candidate starts and
grade the final poses, on either engine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import contract as C
from ..dsa import PreparedDSA
from ..metrics.similarity import mncc
from ..render.renderer import Renderer

__all__ = ["Objective", "PAPER_OBJECTIVE", "ObjectiveValue", "clip_like_target", "objective_value", "generalized_dice_loss"]


@dataclass(frozen=True)
class Objective:
    """The GeoReg objective: ``ncc_weight`` on -mNCC, the rest on the silhouette Dice loss.
    ``clip_drr``: compare the target with the DRR clipped like the target (its
    ``clip_percentiles`` over the DSA mask's columns, then masked) instead of the raw DRR:
    the MAP's silhouette comes from a percentile clip, so the DRR's must too."""

    ncc_weight: float = C.TTO_NCC_WEIGHT
    clip_drr: bool = True
    clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES


#: The paper's objective: the raw DRR against the clipped MAP.
PAPER_OBJECTIVE = Objective(clip_drr=False)


@dataclass(frozen=True)
class ObjectiveValue:
    loss: float
    mncc: float
    dice_loss: float


def clip_like_target(image: np.ndarray, mask: np.ndarray, percentiles: tuple[float, float]) -> np.ndarray:
    """A DRR ``(H, W)`` clipped to its ``percentiles`` over the columns ``mask`` touches, shifted to
    0 and masked: the target's intensity chain (``dsa.preprocess.clip_intensities``) on the DRR."""
    columns = np.asarray(mask).any(axis=0)
    support = image[:, columns] if columns.any() else image
    lo, hi = np.percentile(support, percentiles)
    return (np.clip(image, lo, hi) - lo) * (np.asarray(mask) > 0)


def generalized_dice_loss(pred: np.ndarray, target: np.ndarray) -> float:
    """Two-class generalised Dice loss of a soft mask ``pred`` in [0, 1] and a binary ``target``
    (same definition as ``metrics.losses.generalized_dice_loss``)."""
    p = np.stack((pred, 1.0 - pred)).reshape(2, -1).astype(np.float64)
    g = np.stack((target, 1.0 - target)).reshape(2, -1).astype(np.float64)
    w = 1.0 / np.maximum(g.sum(1), 1.0) ** 2
    total = (w * (p + g).sum(1)).sum()
    return 1.0 - (2.0 * (w * (p * g).sum(1)).sum() / total if total > 0 else 1.0)


def objective_value(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA, objective: Objective = Objective()) -> ObjectiveValue:
    """The objective of one view at ``pose`` ``(4, 4)`` in its acquisition (TTO) geometry."""
    total, cranium = renderer.render(pose, prepared.tto_detector, ("total", "cranium"))
    mask = prepared.tto_mask > 0
    image = clip_like_target(total, mask, objective.clip_percentiles) if objective.clip_drr else total
    score = mncc(prepared.tto_image, image)
    dice = generalized_dice_loss(1.0 / (1.0 + np.exp(-cranium.astype(np.float64))), mask.astype(np.float64))
    w = objective.ncc_weight
    return ObjectiveValue(w * (-score) + (1 - w) * dice, score, dice)
