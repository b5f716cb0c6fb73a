"""Candidate starts of one patient pose (ours): where greedy Refine and the test-time optimisation begin.

One view's Init can be right in rotation and wrong in position, or the other way round, and the
networks can be degrees off where the acquisition's own geometry is nearer. So:

* greedy Refine runs from every combination of the fused Init's and each view's Init's rotation and
  isocentre (:func:`refine_starts`, nine for two views; ``refine.refine_from_starts`` keeps the most
  similar end);
* the TTO's tournament (``tournament.py``) runs from the distinct ones of: the DICOM-angle pose
  (``X = I``), the fused Init, each view's Init alone and the networks' estimate (Refine, with the
  similarity search when it ran), each scored by the objective (:func:`candidate_starts`). Without
  vessel evidence only the DICOM angles start: the silhouette alone cannot tell the others apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..dsa import PreparedDSA
from ..render.renderer import Renderer
from .biplane import view_poses
from .init import InitStage
from ..options import Objective
from .objective import pair_objective

__all__ = ["DICOM_START", "SEARCHED_START", "REFINED_START", "Starts", "refine_starts", "candidate_starts", "same_pose"]

#: The candidate start at the DICOM angles' geometry (``X = I``).
DICOM_START = "DICOM angles"
#: The networks' estimate: greedy Refine, then the similarity search ...
SEARCHED_START = "Refine + search"
#: ... or greedy Refine alone (the search switched off).
REFINED_START = "Refine"


def refine_starts(init: InitStage) -> dict[str, np.ndarray]:
    """Patient poses ``(4, 4)`` that combine the rotation of one Init estimate with the isocentre of
    another, the fused pose among the sources: ``{"rotation A, isocentre B": X}`` for A, B in
    ``fused`` and the views' keys upper-cased (the first is the fused pose)."""
    sources = {"fused": np.asarray(init.patient_pose, dtype=np.float64),
               **{key.upper(): np.asarray(X, dtype=np.float64) for key, X in init.implied.items()}}
    starts = {}
    for rot_name, R in sources.items():
        for iso_name, T in sources.items():
            X = np.array(T)
            X[:3, :3] = R[:3, :3]
            starts[f"rotation {rot_name}, isocentre {iso_name}"] = X
    return starts


def same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two poses ``(4, 4)`` are one start: rotations within 1e-4, positions within 0.01 mm."""
    return bool(np.allclose(a[:3, :3], b[:3, :3], atol=1e-4) and np.allclose(a[:3, 3], b[:3, 3], atol=0.01))


@dataclass(frozen=True)
class Starts:
    """The candidate patient poses ``{name: (4, 4)}`` and their objective (both views summed; lower is better)."""

    poses: Mapping[str, np.ndarray]
    objectives: Mapping[str, float]

    @property
    def best(self) -> str:
        """The start of lowest objective."""
        return min(self.objectives, key=self.objectives.get)

    def distinct(self) -> dict[str, np.ndarray]:
        """The starts with a repeated pose (:func:`same_pose`) left out, the first of each kept."""
        kept: dict[str, np.ndarray] = {}
        for name, X in self.poses.items():
            if not any(same_pose(X, Y) for Y in kept.values()):
                kept[name] = X
        return kept


def candidate_starts(renderer: Renderer, views: Mapping[str, PreparedDSA], rig: Mapping[str, np.ndarray],
                     init: InitStage, learned: Mapping[str, np.ndarray], objective: Objective = Objective(), *,
                     vessel_evidence: bool) -> Starts:
    """The TTO's candidate starts, each scored by the ``objective``: the DICOM angles; with
    ``vessel_evidence`` also the fused Init, each view's Init and the networks' estimate
    (``learned``: ``{name: X}``)."""
    poses = {DICOM_START: np.eye(4)}
    if vessel_evidence:
        poses |= {"Init": init.patient_pose, **{f"Init {key.upper()}": X for key, X in init.implied.items()}, **learned}
    return Starts(poses, {name: pair_objective(renderer, view_poses(X, rig), views, objective) for name, X in poses.items()})
