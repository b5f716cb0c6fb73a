"""The move a registration may make without vessel evidence (numpy).

When the CTA shows no contrast-filled vessels, the objective rests on the head's silhouette
alone, which is flat, or lowest, degrees from the truth on real heads (experiments/tto_objective/silhouette.md), and
the networks' starts are far off on real anatomy. The result then starts from the acquisition's
own geometry (the DICOM angles, patient pose ``X = I``) and its move from there is bounded: a
larger turn of the patient pose, or a larger shift of its isocentre, is scaled back onto the
bound (:func:`~geopose.register.biplane.part_way`). The record and the quality flag say so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np

from ..geometry.poses import matrix_to_axis_angle
from .biplane import part_way

__all__ = ["MAX_ROTATION_DEG", "MAX_SHIFT_MM", "BoundedMove", "bound_move"]

#: The largest turn (deg) and isocentre shift (mm) of the patient pose from the DICOM angles' without
#: vessel evidence: about the head's tilt and placement on the angiography table that the
#: acquisition's geometry leaves (the phantom world draws a 4 deg sd per angle; real heads' DICOM
#: angles lay 6-10 deg off in the benchmark's runs).
MAX_ROTATION_DEG: Final = 8.0
MAX_SHIFT_MM: Final = 40.0


@dataclass(frozen=True)
class BoundedMove:
    """The patient pose kept ``(4, 4)``, the turn (deg) and shift (mm) the optimisation asked for, and
    whether that move was scaled back onto the bound (``fraction`` of it kept)."""

    patient_pose: np.ndarray
    rotation_deg: float
    shift_mm: float
    fraction: float

    @property
    def bounded(self) -> bool:
        return self.fraction < 1.0

    def as_dict(self) -> dict:
        return {"asked_rotation_deg": self.rotation_deg, "asked_shift_mm": self.shift_mm, "kept_fraction": self.fraction,
                "bounded": self.bounded, "max_rotation_deg": MAX_ROTATION_DEG, "max_shift_mm": MAX_SHIFT_MM}


def bound_move(X: np.ndarray, start: np.ndarray | None = None) -> BoundedMove:
    """``X`` ``(4, 4)``, or the pose part of the way from ``start`` (default: the identity, the DICOM angles'
    geometry) to it that lies on the bound (:data:`MAX_ROTATION_DEG`, :data:`MAX_SHIFT_MM`)."""
    start = np.eye(4) if start is None else np.asarray(start, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    rotation_deg = float(np.degrees(np.linalg.norm(matrix_to_axis_angle(X[:3, :3] @ start[:3, :3].T))))
    shift_mm = float(np.linalg.norm(X[:3, 3] - start[:3, 3]))
    fraction = min(1.0, MAX_ROTATION_DEG / max(rotation_deg, 1e-9), MAX_SHIFT_MM / max(shift_mm, 1e-9))
    kept = X if fraction >= 1.0 else part_way(start, X, fraction)
    return BoundedMove(kept, rotation_deg, shift_mm, fraction)
