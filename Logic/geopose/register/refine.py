"""Similarity-gated greedy refinement with GeoPose-Refine (paper section 2.3.2).

Each proposal is ``T_new = inverse(D) @ T_current`` with ``D`` the network's residual
for (target, DRR at ``T_current``); it is accepted only if the multiscale NCC between
target and render strictly increases, and the loop stops at the first rejection or
after ``max_proposals`` (one patient pose seen by both arms: a rejected move is first tried
once at ``RefineOptions.retry_fraction`` of its size). Scores in float64 (a float32
mNCC of flat patches is off by about 0.005, enough to flip a decision). numpy poses; any
renderer and Refine predictor. :func:`greedy_refine` refines one view's camera pose (the
paper); :func:`refine_from_starts` one patient pose seen by both arms, from several starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..geometry.poses import invert
from ..metrics.similarity import MNCCTarget
from ..nets.predictors import RefinePredictor
from ..options import RefineOptions
from ..render.renderer import Renderer
from .biplane import Observability, fuse_patient_poses, part_way, patient_pose
from .calibration import render_model_view
from .progress import Monitor
from .results import Proposal, RefineTrace

__all__ = ["greedy_refine", "refine_from_starts", "StartsRefined"]


def greedy_refine(
    renderer: Renderer,
    target: np.ndarray,
    pose: np.ndarray,
    view: int,
    refine: RefinePredictor,
    render_px: int,
    max_proposals: int = RefineOptions.steps,
    monitor: Monitor | None = None,
) -> RefineTrace:
    """Refine ``pose`` ``(4, 4)`` against a model-geometry ``target`` ``(1, 1, 256, 256)``."""
    monitor = monitor or Monitor()
    mncc = MNCCTarget(target[0, 0])
    current = np.asarray(pose, dtype=np.float64)
    image = render_model_view(renderer, current, render_px)
    start, start_score = current, mncc(image[0, 0])
    score, proposals = start_score, []
    for k in range(max_proposals):
        monitor.step("refine", k / max_proposals, f"proposal {k + 1}/{max_proposals}")
        candidate = invert(refine.predict_residual(target, image, view)[0]) @ current
        cand_image = render_model_view(renderer, candidate, render_px)
        cand_score = mncc(cand_image[0, 0])
        accepted = cand_score > score
        proposals.append(Proposal(candidate, cand_score, accepted))
        if not accepted:
            break
        current, image, score = candidate, cand_image, cand_score
    trace = RefineTrace(start, start_score, current, score, tuple(proposals))
    monitor.step("refine", 1.0, f"{trace.accepted} of {len(trace.proposals)} proposals accepted")
    return trace


@dataclass(frozen=True)
class StartsRefined:
    """Greedy Refine of one patient pose from several starts: the winning start's name, its
    traces per view and every start's final mean mNCC."""

    start: str
    traces: dict[str, RefineTrace]
    mncc: dict[str, float]


def refine_from_starts(
    renderer: Renderer,
    targets: Mapping[str, np.ndarray],
    starts: Mapping[str, np.ndarray],
    rig: Mapping[str, np.ndarray],
    views: Mapping[str, int],
    refine: RefinePredictor,
    render_px: int,
    options: RefineOptions = RefineOptions(),
    observability: Observability = Observability(),
    monitor: Monitor | None = None,
) -> StartsRefined:
    """The gated refinement of one patient pose ``X`` seen by both arms (``T_v = X @ rig[v]``) from each
    pose in ``starts`` ``{name: (4, 4)}``; the end with the highest mean mNCC of the views wins (the first
    in ``starts`` on a tie).

    Each proposal applies every view's Refine residual to its own camera pose, reads the patient
    pose each implies and fuses them by what each view observes (:func:`.biplane.fuse_patient_poses`);
    it is accepted only if the mean mNCC of the views strictly increases; a rejected move is tried
    once more at ``options.retry_fraction`` of its size (rotation and isocentre shift scaled alike) before
    that start stops. Each view's trace holds poses ``X @ A_v``, that view's mNCC and the joint
    accept flags (a retry is a proposal of its own).

    The starts run in lockstep: each step runs Refine once per view on every start still
    improving (one batch), so each start makes the same moves as it would alone."""
    monitor = monitor or Monitor()
    keys = list(rig)
    X = {name: np.asarray(pose, dtype=np.float64) for name, pose in starts.items()}
    similarity = {k: MNCCTarget(targets[k][0, 0]) for k in keys}

    def render_all(poses: Mapping[str, np.ndarray]) -> tuple[dict, dict]:
        """Model-view images ``{start: {view: (1, 1, 256, 256)}}`` and their mNCC ``{start: {view: float}}``."""
        images = {n: {k: render_model_view(renderer, pose @ rig[k], render_px) for k in keys} for n, pose in poses.items()}
        return images, {n: {k: similarity[k](im[k][0, 0]) for k in keys} for n, im in images.items()}

    images, scores = render_all(X)
    first = {n: {k: (X[n] @ rig[k], scores[n][k]) for k in keys} for n in X}
    proposals: dict[str, dict[str, list[Proposal]]] = {n: {k: [] for k in keys} for n in X}
    score = {n: float(np.mean(list(scores[n].values()))) for n in X}
    running = list(X)
    max_proposals = options.steps
    for step in range(max_proposals):
        if not running:
            break
        monitor.step("refine", step / max_proposals,
                     f"proposal {step + 1}/{max_proposals}, {len(running)} of {len(X)} start(s) improving")
        residuals = {k: refine.predict_residual(np.repeat(targets[k], len(running), axis=0),
                                                np.concatenate([images[n][k] for n in running]), views[k]) for k in keys}
        moves = {n: fuse_patient_poses({k: patient_pose(invert(residuals[k][i]) @ (X[n] @ rig[k]), rig[k]) for k in keys},
                                       rig, observability) for i, n in enumerate(running)}
        candidates, improved = dict(moves), []
        for retry in (False, True):
            cand_images, cand_scores = render_all(candidates)
            for n, candidate in candidates.items():
                cand_score = float(np.mean(list(cand_scores[n].values())))
                accepted = cand_score > score[n]
                for k in keys:
                    proposals[n][k].append(Proposal(candidate @ rig[k], cand_scores[n][k], accepted))
                if accepted:
                    X[n], images[n], scores[n], score[n] = candidate, cand_images[n], cand_scores[n], cand_score
                    improved.append(n)
            if not retry:
                candidates = {n: part_way(X[n], moves[n], options.retry_fraction) for n in candidates if n not in improved}
        running = [n for n in running if n in improved]
    traces = {n: {k: RefineTrace(*first[n][k], X[n] @ rig[k], scores[n][k], tuple(proposals[n][k])) for k in keys}
              for n in X}
    best = max(score, key=score.get)
    trace = traces[best][keys[0]]
    monitor.step("refine", 1.0, f"best from {best}: {trace.accepted} of {len(trace.proposals)} proposals accepted")
    return StartsRefined(best, traces[best], score)
