"""The TTO's common-axis search (ours): the turn of a patient pose about the axis both image planes contain.

That turn is out of plane in both views: its gradient is weak, a prior holds it near its start
(``tto.ROTATION_PRIOR_PER_RAD2``), and the objective is flat along it unless the other five
parameters compensate the pixel motion it causes (:func:`valley_turn`). At set fractions of the
TTO's steps the patient pose is moved along that valley to the objective's best (:func:`best_turn`;
``tto.TTOSchedule.axis_search_at``). numpy.
"""

from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from ..geometry.detector import Detector
from ..geometry.poses import project_points
from .biplane import common_axis, moved_by

__all__ = ["valley_turn", "best_turn"]


def valley_turn(
    X: np.ndarray, nominal: Mapping[str, np.ndarray], detectors: Mapping[str, Detector], points_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """The patient motion, per radian of turn about the common axis (:func:`common_axis`), that moves
    the projections of ``points_mm`` ``(N, 3)`` (CTA frame) in the views' ``detectors`` least:
    ``(rotation (3,) rad/rad, shift (3,) mm/rad)`` for :func:`moved_by`, the rotation's part along
    the axis 1. The turn alone shifts the views' images, which the other five parameters
    partly undo (least squares on the pixel motion, linearised at ``X``); the objective is flat
    along this direction rather than along the bare turn. None without a common axis or points."""
    axis = common_axis({k: X for k in nominal}, nominal)
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if axis is None or not len(points):
        return None
    others = np.linalg.svd(axis[None])[2][1:]  # two unit vectors normal to the axis
    basis = np.zeros((6, 6))
    basis[:3, 0], basis[:3, 1:3], basis[3:, 3:] = axis, others.T, np.eye(3)

    def pixels(d: np.ndarray) -> np.ndarray:
        Y = moved_by(X, d[:3], d[3:])
        return np.concatenate([project_points(Y @ nominal[k], detectors[k], points)[0].ravel() for k in nominal])

    eps = 1e-5
    J = np.stack([(pixels(eps * b) - pixels(-eps * b)) / (2 * eps) for b in basis.T], axis=1)
    rest, *_ = np.linalg.lstsq(J[:, 1:], -J[:, 0], rcond=None)
    d = basis @ np.r_[1.0, rest]
    return d[:3], d[3:]



def best_turn(score: Callable[[float], float], step_deg: float) -> tuple[list[float], list[float], float]:
    """The turn (deg) of lowest ``score`` among ``-step, 0, +step`` and, where those three are convex, the
    vertex of the parabola through them (within twice the step): ``(turns, scores, chosen)``."""
    turns = [-step_deg, 0.0, step_deg]
    scores = [score(d) for d in turns]
    curvature = scores[0] + scores[2] - 2 * scores[1]
    if curvature > 0:
        turns.append(float(np.clip(step_deg * (scores[0] - scores[2]) / (2 * curvature), -2 * step_deg, 2 * step_deg)))
        scores.append(score(turns[-1]))
    return turns, scores, turns[int(np.argmin(scores))]
