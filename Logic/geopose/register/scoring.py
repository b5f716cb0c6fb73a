"""The last stage: each view's final scores and quality flag (numpy; either engine).

Per view, in its acquisition (TTO) geometry: the mNCC of the DRR against the MAP, the silhouette
Dice of the projected CTA cranium and the DSA cranium mask, the objective's terms (``evidence.py``),
how far the result moved from the networks' estimate, and the case's consistency checks, read by
the quality flag (``quality.py``).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .. import contract as C
from ..dsa import PreparedDSA
from ..metrics.similarity import mncc
from ..options import Objective
from ..render.renderer import Renderer
from .case import VIEW_KEYS, PreparedCase, silhouette_dice
from .evidence import ViewEvidence, view_evidence
from .quality import VIEW_DISAGREEMENT_MM, Quality, assess
from .results import InitEstimate, RefineTrace, Registration, ViewOutcome
from .trust import stage_agreement

__all__ = ["score_view", "consistency_doubts", "score_views"]


def score_view(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA) -> tuple[float, float]:
    """(mNCC of the DRR at ``pose`` against the TTO target, hard Dice of the projected cranium
    and the DSA cranium mask), both in the TTO geometry (acquisition SDD)."""
    image = renderer.render(pose, prepared.tto_detector, ("total", "cranium"))
    return mncc(prepared.tto_image, image[0]), silhouette_dice(image[1], prepared.tto_mask)


def consistency_doubts(init: InitEstimate, label: int, registration: Registration) -> tuple[str, ...]:
    """The failed consistency checks of one view (its Init, its acquisition's view ``label``), worded for its flag."""
    doubts = []
    if init.network_view != label:
        doubts.append(f"the network reads this view as {C.VIEW_NAMES[init.network_view]} but its acquisition angle says "
                      f"{C.VIEW_NAMES[label]}: check the runs' angles (docs/conventions.md section 7)")
    if not registration.vessel_evidence:
        bound = registration.bound
        doubts.append("no vessel evidence: the CTA shows no contrast-filled vessels, so the pose rests on the head's "
                      "silhouette alone" + ("" if bound is None or not bound.bounded else
                                            f"; its move from the DICOM angles was bounded ({bound.rotation_deg:.1f} deg / "
                                            f"{bound.shift_mm:.0f} mm asked, {100 * bound.fraction:.0f} % kept)"))
    if registration.kept_learned:
        doubts.append(registration.kept_learned)
    apart = registration.checks.get("view_disagreement_mm", 0.0)
    if apart > VIEW_DISAGREEMENT_MM:
        doubts.append(f"the two views place the patient {apart:.0f} mm apart along the axis both see: did the patient move "
                      "between the runs, or are they not one biplane pair?")
    return tuple(doubts)


def score_views(renderer: Renderer, case: PreparedCase, registration: Registration, *, inits: Mapping[str, InitEstimate],
                init_poses: Mapping[str, np.ndarray], refined: Mapping[str, RefineTrace], learned: Mapping[str, np.ndarray],
                finals: Mapping[str, np.ndarray], searched: bool, given_vessels: bool,
                objective: Objective = Objective(),
                measured: Mapping[str, tuple[np.ndarray, ViewEvidence]] | None = None) -> dict[str, ViewOutcome]:
    """Every view's outcome: the stages' poses (``learned``: the networks' estimate; ``finals``: the result) with
    the final scores and flag. The vessel NCC grades a pose only against a given segmentation
    (``given_vessels``): a computed mask holds veins and bone rims, and its NCC stays low at the truth (the
    demo phantom: 0.05-0.13 at 2 mm mPCD). ``measured``: evidence already measured, ``(pose, evidence)`` per view,
    reused where that pose is the final one."""
    outcomes = {}
    for key in VIEW_KEYS:
        view = case.views[key]
        score, dice = score_view(renderer, finals[key], view)
        known = (measured or {}).get(key)
        reuse = known is not None and np.array_equal(known[0], finals[key])
        evidence = known[1] if reuse else view_evidence(renderer, finals[key], view, objective)
        quality: Quality = assess(score, dice, *stage_agreement(learned[key], finals[key]),
                                  evidence=evidence if given_vessels else None, mirror=registration.mirror,
                                  pairing=registration.pairing,
                                  doubts=consistency_doubts(inits[key], view.view_label, registration))
        outcomes[key] = ViewOutcome(key, view, inits[key], init_poses[key], refined[key], finals[key], score, dice, quality,
                                    learned[key] if searched else None, evidence)
    return outcomes
