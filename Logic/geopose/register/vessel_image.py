"""Which of a run's vessel images the objective compares: the CTA's vessels, rendered at the networks' estimate, pick.

Each run has two (``dsa.preprocess``): the frames weighted by the run's bolus curve (``tto_vessels``, the default) and
the mean of its first half (``tto_vessels_early``). The bolus curve is read from the brightest fine detail of the run;
in a short run whose late frames carry the capillary blush's rim and motion residue it follows those frames, and the
weighted image shows no artery (validation 6010 LAT: NCC -0.001 with the true arteries' projection, 0.69 for the first
half). At the networks' estimate (2-3 mm off) the CTA's vessels, veins included, still tell a broken image from a
working one, but not two working ones apart, so the first half is used only where its NCC with their render beats the
bolus image's by :data:`EARLY_IMAGE_LEAD`. On validation 6010-6034 that switched only 6010 LAT; on 30 views of dense
runs (every territory, an AVM, a late venous phase) none (experiments/vessel_image/candidates.md). The plain mean is no
candidate: in a late venous run it matches the computed mask's veins best and shows the arteries worst. numpy poses;
any renderer.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np

from ..dsa import PreparedDSA
from ..metrics.similarity import ncc
from ..render.renderer import Renderer

__all__ = ["EARLY_IMAGE_LEAD", "VesselImageChoice", "choose_vessel_images"]

#: The NCC (with the CTA's vessels at the networks' estimate) by which the run's first half must beat the bolus-weighted
#: image to replace it. Elsewhere on validation the largest lead was 0.038; 6010 LAT's was 0.169.
EARLY_IMAGE_LEAD = 0.05


@dataclass(frozen=True)
class VesselImageChoice:
    """One view's vessel image: ``used`` (``"bolus"`` or ``"early"``) and each candidate's NCC with the DRR of the
    CTA's vessel channel at the networks' estimate (``ncc``)."""

    used: str
    ncc: dict[str, float]


def choose_vessel_images(renderer: Renderer, views: Mapping[str, PreparedDSA], poses: Mapping[str, np.ndarray]
                         ) -> tuple[dict[str, PreparedDSA], dict[str, VesselImageChoice]]:
    """Each view with the vessel image its objective compares (a copy whose ``tto_vessels`` is the run's first half,
    where that won; else the view itself) and the choice, from ``poses`` ``{view: (4, 4)}`` (the networks' estimate,
    camera-to-world, centred CTA frame). A view without an early image, or a CTA without vessels, keeps its own."""
    chosen, choices = {}, {}
    for key, view in views.items():
        chosen[key] = view
        if view.tto_vessels_early is None:
            continue
        vessels = renderer.render(poses[key], view.tto_detector, ("vessels",))[0].astype(np.float64)
        if not vessels.max() > 0:
            continue
        scores = {name: float(ncc(image.astype(np.float64), vessels))
                  for name, image in (("bolus", view.tto_vessels), ("early", view.tto_vessels_early))}
        used = "early" if scores["early"] >= scores["bolus"] + EARLY_IMAGE_LEAD else "bolus"
        choices[key] = VesselImageChoice(used, {name: round(value, 4) for name, value in scores.items()})
        if used == "early":
            chosen[key] = replace(view, tto_vessels=view.tto_vessels_early)
    return chosen, choices
