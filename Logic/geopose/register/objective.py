"""The registration objective, as a score (numpy; no gradients).

Per view, in the acquisition geometry: the GeoReg silhouette terms ``w * (-mNCC(target,
image)) + (1 - w) * GeneralizedDice(sigmoid(cranium channel), DSA mask)``, ``image`` the DRR
clipped like the target, and a vessel term ``-NCC(MAP vessels, DRR vessel channel)``
weighted ``vessel_weight`` against them (:class:`Objective`). The MAP's head silhouette is
made by quantum noise, whose level follows the attenuation of the whole head (face and
neck included): at the true pose it lies 1-4 px off the CTA's silhouette, so the
silhouette terms alone have their optimum 1-3 mm from the truth; the opacified vessels
are sharp and sit where the CTA's vessels project (docs/objective.md). The same
objective, differentiable, is what the test-time optimisation minimises (``tto.py``);
scores here decide between candidate starts and grade the final poses, on either engine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import contract as C
from ..dsa import PreparedDSA
from ..metrics.similarity import mncc, ncc
from ..render.renderer import Renderer

__all__ = ["Objective", "PAPER_OBJECTIVE", "ObjectiveValue", "clip_like_target", "combine", "objective_value",
           "generalized_dice_loss"]


@dataclass(frozen=True)
class Objective:
    """The objective's weights: ``vessel_weight`` on the vessel term (-NCC of the MAP's vessels
    and the DRR's vessel channel; 0 where the CTA has no vessel channel), the rest on the
    GeoReg silhouette terms, of which ``ncc_weight`` on -mNCC and the rest on the Dice loss.
    ``clip_drr``: compare the silhouette target with the DRR clipped like it (its
    ``clip_percentiles`` over the DSA mask's columns, then masked) instead of the raw DRR.
    ``read_opacified``: the TTO reads which vessels the runs show opacified after its coarse steps
    and compares those alone from then on (``opacified.py``)."""

    ncc_weight: float = C.TTO_NCC_WEIGHT
    clip_drr: bool = True
    clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES
    vessel_weight: float = 0.75
    read_opacified: bool = True


#: The paper's objective: the raw DRR against the clipped MAP, no vessel term.
PAPER_OBJECTIVE = Objective(clip_drr=False, vessel_weight=0.0, read_opacified=False)


@dataclass(frozen=True)
class ObjectiveValue:
    """The loss and its terms: silhouette mNCC, Dice loss, vessel NCC (None: no vessel term)."""

    loss: float
    mncc: float
    dice_loss: float
    vessel_ncc: float | None


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


def combine(objective: Objective, mncc_value, dice_loss, vessel_ncc):
    """The loss from its terms (numbers or torch tensors alike; ``vessel_ncc`` None: no vessel term)."""
    silhouette = objective.ncc_weight * (-mncc_value) + (1 - objective.ncc_weight) * dice_loss
    if vessel_ncc is None or objective.vessel_weight == 0:
        return silhouette
    return (1 - objective.vessel_weight) * silhouette + objective.vessel_weight * (-vessel_ncc)


def objective_value(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA, objective: Objective = Objective()) -> ObjectiveValue:
    """The objective of one view at ``pose`` ``(4, 4)`` in its acquisition (TTO) geometry."""
    total, cranium, vessels = renderer.render(pose, prepared.tto_detector, ("total", "cranium", "vessels"))
    mask = prepared.tto_mask > 0
    image = clip_like_target(total, mask, objective.clip_percentiles) if objective.clip_drr else total
    score = mncc(prepared.tto_image, image)
    dice = generalized_dice_loss(1.0 / (1.0 + np.exp(-cranium.astype(np.float64))), mask.astype(np.float64))
    vessel = ncc(prepared.tto_vessels, vessels) if objective.vessel_weight > 0 and vessels.max() > 0 else None
    return ObjectiveValue(float(combine(objective, score, dice, vessel)), score, dice, vessel)
