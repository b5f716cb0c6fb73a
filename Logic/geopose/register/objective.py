"""The registration objective, as a score (numpy; no gradients).

Per view, in the acquisition geometry: the GeoReg silhouette terms ``w * (-mNCC(target,
image)) + (1 - w) * GeneralizedDice(sigmoid(cranium channel), DSA mask)``, ``image`` the DRR
brought to the target's intensities (by default fitted to it, :func:`fit_like_target`), and a
vessel term ``-NCC(MAP vessels, DRR vessel channel)`` weighted ``vessel_weight`` against them
(:class:`Objective`). The MAP's head silhouette is made by quantum noise, whose level grows
like exp(attenuation / 2) through the whole head (face and neck included), so a linear DRR
clipped like the MAP has its optimum 1-3 deg from the truth on heads without vessels; a model
of that level fitted to the MAP lies nearer on most (experiments/tto_objective/silhouette.md). The opacified vessels
are sharp and sit where the CTA's vessels project (experiments/tto_objective/objective.md). The same
objective, differentiable, is what the test-time optimisation minimises (``tto.py``);
scores here decide between candidate starts and grade the final poses, on either engine.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any, Mapping

import numpy as np

from .. import contract as C
from ..dsa import PreparedDSA
from ..metrics.similarity import mncc, ncc
from ..render.renderer import Renderer

__all__ = ["Objective", "PAPER_OBJECTIVE", "ObjectiveValue", "SILHOUETTE_MODELS", "clip_like_target", "fit_like_target",
           "silhouette_features", "combine", "objective_value", "pair_objective", "generalized_dice_loss"]

#: A numpy array or a torch tensor (the fitted silhouette serves both engines).
Array = Any

#: How the DRR's total channel is compared with the silhouette target: ``raw`` (the paper), ``clipped``
#: like the target (:func:`clip_like_target`) or ``fitted`` to it (:func:`fit_like_target`).
SILHOUETTE_MODELS = ("raw", "clipped", "fitted")


@dataclass(frozen=True)
class Objective:
    """The objective's weights: ``vessel_weight`` on the vessel term (-NCC of the MAP's vessels
    and the DRR's vessel channel; 0 where the CTA has no vessel channel), the rest on the
    GeoReg silhouette terms, of which ``ncc_weight`` on -mNCC and the rest on the Dice loss.
    ``silhouette``: the DRR the silhouette target is compared with (:data:`SILHOUETTE_MODELS`):
    ``raw``, ``clipped`` (to its ``clip_percentiles`` over the DSA mask's columns, then masked)
    or ``fitted`` (the noise-level model least-squares fitted to the target inside the mask,
    :func:`fit_like_target`); ``coarse_silhouette``: the same at the TTO's half-size steps. The
    fitted model's optimum lies nearest the truth, but it adapts its intensities to any pose, so far
    from the truth it also rewards wrong ones; the clipped DRR's fixed mapping draws a start
    10 deg off in, so the coarse steps use it (experiments/tto_objective/silhouette.md).
    ``read_opacified``: the TTO reads which vessels the runs show opacified after its coarse steps
    and compares those alone from then on (``opacified.py``)."""

    ncc_weight: float = C.TTO_NCC_WEIGHT
    silhouette: str = "fitted"
    coarse_silhouette: str = "clipped"
    clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES
    vessel_weight: float = 0.75
    read_opacified: bool = True

    def __post_init__(self) -> None:
        for name in ("silhouette", "coarse_silhouette"):
            if getattr(self, name) not in SILHOUETTE_MODELS:
                raise ValueError(f"{name} must be one of {SILHOUETTE_MODELS}, got {getattr(self, name)!r}")


#: The paper's objective: the raw DRR against the clipped MAP, no vessel term.
PAPER_OBJECTIVE = Objective(silhouette="raw", coarse_silhouette="raw", vessel_weight=0.0, read_opacified=False)


@dataclass(frozen=True)
class ObjectiveValue:
    """The loss and its terms: silhouette mNCC, Dice loss, vessel NCC (None: no vessel term)."""

    loss: float
    mncc: float
    dice_loss: float
    vessel_ncc: float | None


def clip_like_target(image: Array, mask: Array, percentiles: tuple[float, float], xp: ModuleType = np) -> Array:
    """A DRR ``(H, W)`` clipped to its ``percentiles`` over the columns ``mask`` touches, shifted to
    0 and masked: the target's intensity chain (``dsa.preprocess.clip_intensities``) on the DRR.
    numpy, or torch with ``xp=torch`` (the bounds carry no gradient)."""
    inside = mask > 0
    columns = inside.any(0)
    values = _detached(image)
    support = values[:, columns] if bool(columns.any()) else values
    lo, hi = (float(xp.quantile(support, p / 100.0)) for p in percentiles)
    return (xp.clip(image, lo, hi) - lo) * inside


def silhouette_features(image: Array, mask: Array, xp: ModuleType = np) -> Array:
    """The fitted silhouette's basis ``(3, H, W)`` from a DRR ``(H, W)`` (numpy, or torch with ``xp=torch``):
    u, exp(k min(u, 1)) and 1, with u the DRR over its 99.5th percentile inside ``mask``."""
    values = _constant(image)  # the scale is a constant to the gradient
    inside = values[mask > 0] if bool((mask > 0).any()) else values.reshape(-1)
    u = image / max(float(xp.quantile(inside, C.SILHOUETTE_NORM_PERCENTILE / 100.0)), 1e-6)
    return xp.stack((u, xp.exp(C.SILHOUETTE_NOISE_EXPONENT * xp.clip(u, None, 1.0)), xp.ones_like(u)))


def _detached(a: Array) -> Array:
    """``a`` detached from any gradient (numpy or torch)."""
    return a.detach() if hasattr(a, "detach") else np.asarray(a)


def _constant(a: Array) -> Array:
    """``a`` in float64, detached from any gradient (numpy or torch)."""
    a = _detached(a)
    return a.double() if hasattr(a, "double") else a.astype(np.float64)


#: The supports the fitted silhouette's weights are tried on: the offset always, the DRR and the noise
#: level each only with a non-negative weight (brighter where the head is thicker, never inverted).
_SUPPORTS = ((0, 1, 2), (0, 2), (1, 2), (2,))


def fit_like_target(image: Array, target: Array, mask: Array, xp: ModuleType = np) -> Array:
    """A DRR ``(H, W)`` mapped onto the silhouette ``target``'s intensities, masked: the combination of
    :func:`silhouette_features` closest to ``target`` inside ``mask`` (least squares with non-negative
    weights on the DRR and the noise level; the weights carry no gradient). numpy, or torch with ``xp=torch``."""
    inside = mask > 0
    basis = silhouette_features(image, mask, xp)
    a, b = _constant(basis[:, inside]), _constant(target[inside])
    gram, moment = a @ a.T, a @ b
    best, best_residual = None, float("inf")
    for support in _SUPPORTS:
        s = list(support)
        w = xp.linalg.pinv(gram[s][:, s]) @ moment[s]  # a pseudo-inverse: a flat DRR (head out of view) has no unique fit
        residual = float(-2.0 * (w * moment[s]).sum() + w @ gram[s][:, s] @ w)  # the residual less |b|^2
        if bool((w[:-1] >= 0).all()) and residual < best_residual:
            best, best_residual = xp.zeros_like(moment), residual
            best[s] = w
    weights = best.to(basis.dtype) if hasattr(best, "to") else best
    return (weights[:, None, None] * basis).sum(0) * inside


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
    if objective.silhouette == "clipped":
        image = clip_like_target(total, mask, objective.clip_percentiles)
    elif objective.silhouette == "fitted":
        image = fit_like_target(total.astype(np.float64), prepared.tto_image, mask)
    else:
        image = total
    score = mncc(prepared.tto_image, image)
    dice = generalized_dice_loss(1.0 / (1.0 + np.exp(-cranium.astype(np.float64))), mask.astype(np.float64))
    vessel = ncc(prepared.tto_vessels, vessels) if objective.vessel_weight > 0 and vessels.max() > 0 else None
    return ObjectiveValue(float(combine(objective, score, dice, vessel)), score, dice, vessel)


def pair_objective(renderer: Renderer, poses: "Mapping[str, np.ndarray]", views: "Mapping[str, PreparedDSA]") -> float:
    """The objective of every view in ``views`` at its pose in ``poses``, summed: how starts, TTO runs and
    hypotheses are compared."""
    return float(sum(objective_value(renderer, poses[k], views[k]).loss for k in views))
