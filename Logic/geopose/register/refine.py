"""Similarity-gated greedy refinement with GeoPose-Refine (paper section 2.3.2).

Each proposal is ``T_new = inverse(D) @ T_current`` with ``D`` the network's residual
for (target, DRR at ``T_current``); it is accepted only if the multiscale NCC between
target and render strictly increases, and the loop stops at the first rejection or
after ``max_proposals``. Scores in float64 (a float32 mNCC of flat patches is off by
about 0.005, enough to flip a decision). numpy poses; any renderer and Refine predictor.
"""

from __future__ import annotations

import numpy as np

from .. import contract as C
from ..geometry.poses import invert
from ..metrics.similarity import mncc
from ..nets.predictors import RefinePredictor
from ..render.renderer import Renderer
from .calibration import render_model_view
from .progress import Monitor
from .results import Proposal, RefineTrace

__all__ = ["greedy_refine"]


def greedy_refine(
    renderer: Renderer,
    target: np.ndarray,
    pose: np.ndarray,
    view: int,
    refine: RefinePredictor,
    render_px: int,
    max_proposals: int = C.GREEDY_MAX_PROPOSALS,
    monitor: Monitor | None = None,
) -> RefineTrace:
    """Refine ``pose`` ``(4, 4)`` against a model-geometry ``target`` ``(1, 1, 256, 256)``."""
    monitor = monitor or Monitor()
    current = np.asarray(pose, dtype=np.float64)
    image = render_model_view(renderer, current, render_px)
    score = mncc(target[0, 0], image[0, 0])
    trace = RefineTrace(current, score, current, score)
    for k in range(max_proposals):
        monitor.step("refine", k / max_proposals, f"proposal {k + 1}/{max_proposals}")
        candidate = invert(refine.predict_residual(target, image, view)[0]) @ current
        cand_image = render_model_view(renderer, candidate, render_px)
        cand_score = mncc(target[0, 0], cand_image[0, 0])
        accepted = cand_score > score
        trace.proposals.append(Proposal(candidate, cand_score, accepted))
        if not accepted:
            break
        current, image, score = candidate, cand_image, cand_score
    trace.pose, trace.mncc = current, score
    monitor.step("refine", 1.0, f"{trace.accepted} of {len(trace.proposals)} proposals accepted")
    return trace
