"""Similarity search of one patient pose seen by both arms (ours, not the paper's).

After greedy Refine, a derivative-free pattern search moves the patient pose ``X`` by what
both views observe in-plane: the isocentre shift along each CTA axis (mm) and the turn about
each view's central ray (deg; that view's in-plane rotation). Each move is tried in both
directions at each step size of ``options.SearchOptions.schedule``; an improvement of the
views' mean mNCC (float64) between the model-geometry target and the DRR, both at that step's
image size, is kept and the directions are tried again, but for the one back to the pose just
left (it scored lower); a step size ends when no move improves. The coarse steps score small images (the renderer then samples a coarser CTA
level: a third of the time), the finest the networks' render size. The turn about the axis
both views share is left to the TTO: it barely changes either image (``axis_search.valley_turn``).
No PyTorch: it runs on either engine, so the torch-free engine's result gains it too. numpy
poses (centred CTA frame, RAS axes x, y, z); any renderer.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..geometry.detector import Detector
from ..images import resize_bilinear
from ..metrics.similarity import MNCCTarget
from ..options import SearchOptions
from ..render.renderer import Renderer
from .biplane import central_ray, moved_by
from .progress import Monitor
from .results import SearchTrace

__all__ = ["similarity_search"]


def _moves(X: np.ndarray, rig: Mapping[str, np.ndarray]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name, rotation (3,) rad per deg, shift (3,) mm per mm)`` of each searched parameter at ``X``."""
    moves = [(f"shift {axis} (mm)", np.zeros(3), e) for axis, e in zip("xyz", np.eye(3))]
    moves += [(f"turn about the {key.upper()} ray (deg)", np.radians(1.0) * central_ray(X, rig[key]), np.zeros(3))
              for key in rig]
    return moves


def similarity_search(
    renderer: Renderer,
    targets: Mapping[str, np.ndarray],
    patient: np.ndarray,
    rig: Mapping[str, np.ndarray],
    render_px: int,
    schedule: tuple[tuple[float, int | None], ...] = SearchOptions.schedule,
    monitor: Monitor | None = None,
) -> SearchTrace:
    """Search the patient pose ``patient`` ``(4, 4)`` (camera poses ``X @ rig[v]``) against the
    model-geometry ``targets`` ``{view: (1, 1, 256, 256)}``; ``schedule``: ``(step, image px)``
    coarse to fine, the step in mm of shift and deg of turn, the image size of its scores (None:
    ``render_px``). Returns the start and end with the views' mean mNCC at the finest size, the
    moves kept and the number of poses scored."""
    monitor = monitor or Monitor()
    X = np.asarray(patient, dtype=np.float64)
    keys = list(rig)
    start, moves, evaluations = X, [], [0]

    def scorer(px: int):
        """The views' mean mNCC of a patient pose, both images at ``px`` pixels per side."""
        detector = Detector.model().resized(px)
        small = {k: MNCCTarget(resize_bilinear(targets[k][0], (px, px))[0]) for k in keys}

        def score(Y: np.ndarray) -> float:
            images = renderer.render(np.stack([Y @ rig[k] for k in keys]), detector, ("total",))
            evaluations[0] += 1
            return float(np.mean([small[k](images[j, 0]) for j, k in enumerate(keys)]))

        return score

    start_mncc = scorer(schedule[-1][1] or render_px)(X)
    for i, (size, px) in enumerate(schedule):
        monitor.step("search", i / len(schedule), f"step {size:g} ({evaluations[0]} poses scored)")
        score = scorer(px or render_px)
        best = score(X)
        improved, back = True, None
        while improved:
            improved = False
            for name, turn, shift in _moves(X, rig):
                for sign in (1.0, -1.0):
                    if (name, sign) == back:  # the pose just left: it scored lower
                        continue
                    candidate = moved_by(X, sign * size * turn, sign * size * shift)
                    value = score(candidate)
                    if value > best:
                        X, best, improved, back = candidate, value, True, (name, -sign)
                        moves.append((name, sign * size))
                        break
                if improved:
                    break
    monitor.step("search", 1.0, f"{len(moves)} moves kept of {evaluations[0]} poses scored")
    return SearchTrace(start, start_mncc, X, best, tuple(moves), evaluations[0])
