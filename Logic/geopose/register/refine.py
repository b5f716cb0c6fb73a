"""Similarity-gated greedy refinement with GeoPose-Refine (paper section 2.3.2).

Each proposal is ``T_new = inverse(D) @ T_current``; it is accepted only if the
multiscale NCC between target and render strictly increases, and the loop stops
at the first rejection or after ``max_proposals``.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from .. import contract as C
from ..geometry import RigidTransform
from ..metrics import mncc
from ..nets import RefinePredictor
from ..render import DRR
from .calibration import render_model_view
from .progress import Monitor
from .results import Proposal, RefineTrace

__all__ = ["greedy_refine"]


@torch.no_grad()
def greedy_refine(
    drr: DRR,
    target: Tensor,
    pose: Tensor,
    view: int,
    refine: RefinePredictor,
    max_proposals: int = C.GREEDY_MAX_PROPOSALS,
    render: Callable[[DRR, Tensor], Tensor] = render_model_view,
    monitor: Monitor | None = None,
) -> RefineTrace:
    """Refine ``pose`` ``(1, 4, 4)`` against a model-geometry ``target`` ``(1, 1, 256, 256)``."""
    monitor = monitor or Monitor()
    current = pose
    image = render(drr, current)
    score = float(mncc(target, image))
    trace = RefineTrace(pose, score, pose, score)
    for k in range(max_proposals):
        monitor.step("refine", k / max_proposals, f"proposal {k + 1}/{max_proposals}")
        residual = refine.predict_residual(target, image, view).to(current.dtype)
        candidate = RigidTransform(residual).inverse().matrix @ current
        cand_image = render(drr, candidate)
        cand_score = float(mncc(target, cand_image))
        accepted = cand_score > score
        trace.proposals.append(Proposal(candidate, cand_score, accepted))
        if not accepted:
            break
        current, image, score = candidate, cand_image, cand_score
    trace.pose, trace.mncc = current, score
    monitor.step("refine", 1.0, f"{trace.accepted} of {len(trace.proposals)} proposals accepted")
    return trace
