"""What the images say about a registered pose, per view (numpy; no PyTorch): the objective's
terms (``objective.py``) at the final pose, which the quality flag reads."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..dsa import PreparedDSA
from ..render.renderer import Renderer
from ..options import Objective
from .objective import ObjectiveValue, objective_value

__all__ = ["ViewEvidence", "view_evidence"]


@dataclass(frozen=True)
class ViewEvidence:
    """One view's objective terms at the final pose."""

    final: ObjectiveValue

    @property
    def vessel_ncc(self) -> float | None:
        """NCC of the run's vessel image and the CTA's projected vessels (None: the objective had no vessel term)."""
        return self.final.vessel_ncc

    def as_dict(self) -> dict:
        return {"vessel_ncc": self.final.vessel_ncc, "silhouette_mncc": self.final.mncc,
                "dice_loss": float(self.final.dice_loss), "loss": self.final.loss}


def view_evidence(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA,
                  objective: Objective = Objective()) -> ViewEvidence:
    """The ``objective`` of one view at ``pose`` ``(4, 4)`` in its acquisition geometry."""
    return ViewEvidence(objective_value(renderer, pose, prepared, objective))
