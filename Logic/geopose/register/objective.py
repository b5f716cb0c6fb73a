"""The registration objective, written once for both engines: scores in numpy, and the same, differentiable,
in torch for the test-time optimisation (:func:`view_terms`; only the similarity kernels are written twice,
``metrics.similarity`` and ``metrics.losses``).

Per view, in the acquisition geometry: the GeoReg silhouette terms ``w * (-mNCC(target,
image)) + (1 - w) * GeneralizedDice(sigmoid(cranium channel), DSA mask)``, ``image`` the DRR
brought to the target's intensities (by default fitted to it, :func:`fit_like_target`), and a
vessel term ``-NCC(MAP vessels, DRR vessel channel)`` weighted ``vessel_weight`` against them
(:class:`Objective`). The MAP's head silhouette is made by quantum noise, whose level grows
like exp(attenuation / 2) through the whole head (face and neck included), so a linear DRR
clipped like the MAP has its optimum 1-3 deg from the truth on heads without vessels; a model
of that level fitted to the MAP lies nearer on most (experiments/tto_objective/silhouette.md). The opacified vessels
are sharp and sit where the CTA's vessels project (experiments/tto_objective/objective.md). The
test-time optimisation minimises it (``tto.py``); its scores decide between candidate starts and
TTO results and grade the final poses, on either engine.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any, Mapping

import numpy as np

from ..dsa import PreparedDSA
from ..metrics.similarity import generalized_dice_loss, mncc, ncc
from ..options import SILHOUETTE_MODELS, Objective
from ..render.renderer import Renderer

__all__ = ["Objective", "PAPER_OBJECTIVE", "ObjectiveValue", "SILHOUETTE_MODELS", "clip_like_target", "fit_like_target",
           "silhouette_features", "combine", "view_terms", "objective_value", "pair_objective"]

#: A numpy array or a torch tensor (the fitted silhouette serves both engines).
Array = Any

#: The fitted silhouette (:func:`fit_like_target`) models the MAP's brightness as a + b u + c exp(k u), u the
#: DRR over its 99.5th percentile inside the DSA mask: quantum noise (log domain) has an sd growing like
#: exp(attenuation / 2), and the thickest head path attenuates about e^-4, so k = 2 (experiments/tto_objective/silhouette.md).
SILHOUETTE_NOISE_EXPONENT = 2.0
SILHOUETTE_NORM_PERCENTILE = 99.5


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
    u = image / max(float(xp.quantile(inside, SILHOUETTE_NORM_PERCENTILE / 100.0)), 1e-6)
    return xp.stack((u, xp.exp(SILHOUETTE_NOISE_EXPONENT * xp.clip(u, None, 1.0)), xp.ones_like(u)))


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


def combine(objective: Objective, mncc_value, dice_loss, vessel_ncc):
    """The loss from its terms (numbers or torch tensors alike; ``vessel_ncc`` None: no vessel term)."""
    silhouette = objective.ncc_weight * (-mncc_value) + (1 - objective.ncc_weight) * dice_loss
    if vessel_ncc is None or objective.vessel_weight == 0:
        return silhouette
    return (1 - objective.vessel_weight) * silhouette + objective.vessel_weight * (-vessel_ncc)


class _NumpyKernels:
    """The objective's similarity and Dice kernels on ``(H, W)`` numpy arrays (float64 scores)."""

    @staticmethod
    def fit_input(total: np.ndarray) -> np.ndarray:
        return total.astype(np.float64)

    mncc = staticmethod(mncc)
    ncc = staticmethod(ncc)

    @staticmethod
    def dice_loss(cranium: np.ndarray, mask: np.ndarray) -> float:
        return generalized_dice_loss(1.0 / (1.0 + np.exp(-cranium.astype(np.float64))), mask.astype(np.float64))


class _TorchKernels:
    """The same on ``(H, W)`` torch tensors, differentiable (values ``(1,)``)."""

    @staticmethod
    def fit_input(total):
        return total

    @staticmethod
    def mncc(a, b):
        from ..metrics.losses import mncc_similarity

        return mncc_similarity(a[None, None], b[None, None])

    @staticmethod
    def ncc(a, b):
        from ..metrics.losses import ncc_similarity

        return ncc_similarity(a[None, None], b[None, None])

    @staticmethod
    def dice_loss(cranium, mask):
        import torch

        from ..metrics.losses import generalized_dice_loss as dice

        return dice(torch.sigmoid(cranium[None, None]), mask[None, None])


def view_terms(total: Array, cranium: Array, vessels: Array, target: Array, mask: Array, vessel_target: Array,
               objective: Objective = Objective(), *, coarse: bool = False, vessel_term: bool | None = None,
               xp: ModuleType = np) -> tuple:
    """``(loss, mNCC, Dice loss, vessel NCC or None)`` of one view from its DRR channels ``total``, ``cranium``,
    ``vessels`` and its targets: the silhouette ``target``, the DSA cranium ``mask`` and the MAP's vessel image
    ``vessel_target``, all ``(H, W)`` in its acquisition geometry. numpy, or torch (differentiable) with
    ``xp=torch``: the one objective of both engines, only the similarity kernels differ. ``coarse``: the TTO's
    half-size steps (``objective.coarse_silhouette``); ``vessel_term``: whether the vessel term counts (None:
    wherever the vessel channel is not empty and ``objective.vessel_weight`` > 0)."""
    kernels = _NumpyKernels if xp is np else _TorchKernels
    model = objective.coarse_silhouette if coarse else objective.silhouette
    if model == "clipped":
        image = clip_like_target(total, mask, objective.clip_percentiles, xp=xp)
    elif model == "fitted":
        image = fit_like_target(kernels.fit_input(total), target, mask, xp=xp)
    else:
        image = total
    if vessel_term is None:
        vessel_term = objective.vessel_weight > 0 and float(vessels.max()) > 0
    similarity = kernels.mncc(target, image)
    dice = kernels.dice_loss(cranium, mask)
    vessel = kernels.ncc(vessel_target, vessels) if vessel_term else None
    return combine(objective, similarity, dice, vessel), similarity, dice, vessel


def objective_value(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA, objective: Objective = Objective()) -> ObjectiveValue:
    """The objective of one view at ``pose`` ``(4, 4)`` in its acquisition (TTO) geometry."""
    total, cranium, vessels = renderer.render(pose, prepared.tto_detector, ("total", "cranium", "vessels"))
    loss, *terms = view_terms(total, cranium, vessels, prepared.tto_image, prepared.tto_mask > 0, prepared.tto_vessels,
                              objective)
    return ObjectiveValue(float(loss), *terms)


def pair_objective(renderer: Renderer, poses: "Mapping[str, np.ndarray]", views: "Mapping[str, PreparedDSA]",
                   objective: Objective = Objective()) -> float:
    """The objective of every view in ``views`` at its pose in ``poses``, summed: how starts, TTO runs and
    hypotheses are compared."""
    return float(sum(objective_value(renderer, poses[k], views[k], objective).loss for k in views))
