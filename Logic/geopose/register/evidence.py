"""What the images say about a registered pose, per view (numpy; no PyTorch): the objective's
terms at the final pose and at its left-right mirror image.

The mirror test asks whether the CTA explains the run better mirrored: a header whose left and
right are swapped still fits the head's nearly symmetric silhouette, but a one-sided injection's
vessels then lie on the wrong side. The mirrored CTA rendered at a pose ``T`` is the CTA rendered
at ``M @ T``, ``M`` the reflection across the sagittal plane through the cranium's centroid
(centred native frame, mm), so no second volume is built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..dsa import PreparedDSA
from ..render.renderer import Renderer
from ..render.volume import RenderVolume
from .objective import ObjectiveValue, objective_value

__all__ = ["ViewEvidence", "midline_mirror", "view_evidence"]


@dataclass(frozen=True)
class ViewEvidence:
    """One view's objective terms at the final pose (``final``) and at its mirror image (``mirrored``)."""

    final: ObjectiveValue
    mirrored: ObjectiveValue

    @property
    def has_vessels(self) -> bool:
        """Whether the objective had a vessel term (the CTA's vessel mask projects into the view)."""
        return self.final.vessel_ncc is not None

    @property
    def mirror_margin(self) -> float | None:
        """Vessel NCC of the pose less that of its mirror image (None without a vessel term): below 0, the
        runs' vessels fit the left-right mirrored CTA better."""
        if self.final.vessel_ncc is None or self.mirrored.vessel_ncc is None:
            return None
        return self.final.vessel_ncc - self.mirrored.vessel_ncc

    def as_dict(self) -> dict:
        return {"vessel_ncc": self.final.vessel_ncc, "silhouette_mncc": self.final.mncc, "dice_loss": self.final.dice_loss,
                "loss": self.final.loss, "mirrored_vessel_ncc": self.mirrored.vessel_ncc,
                "mirrored_loss": self.mirrored.loss, "mirror_margin": self.mirror_margin}


def midline_mirror(volume: RenderVolume) -> np.ndarray:
    """The reflection ``(4, 4)`` across the plane x = c of the centred native frame (RAS x: left-right),
    c the x of the cranium mask's centroid (mm)."""
    k, j, i = np.nonzero(volume.mask("cranium"))
    centroid = volume.cta.ijk_to_centred @ np.array([i.mean(), j.mean(), k.mean(), 1.0])
    mirror = np.eye(4)
    mirror[0, 0], mirror[0, 3] = -1.0, 2.0 * centroid[0]
    return mirror


def view_evidence(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA, mirror: np.ndarray) -> ViewEvidence:
    """The objective (``objective.py``, default weights) at ``pose`` ``(4, 4)`` and at ``mirror @ pose``."""
    return ViewEvidence(objective_value(renderer, pose, prepared), objective_value(renderer, mirror @ pose, prepared))
