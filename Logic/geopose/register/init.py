"""Calibrated GeoPose-Init of both views, as one patient pose (ours; the paper registers each view alone).

Each view's Init (``calibration.calibrated_init``, its lateral side fixed by the acquisition angle)
implies a patient pose ``X_v = T_v @ inverse(A_v)`` (``biplane.py``); the two are fused by what each
view observes. How far apart they put the patient along the axis both views see is a consistency
check of the pair (did the patient move between the runs?).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..nets.predictors import InitPredictor
from .biplane import axis_disagreement_mm, fuse_patient_poses, patient_pose
from .calibration import calibrated_init
from .case import VIEW_KEYS, PreparedCase
from .progress import Monitor
from .results import Calibration, InitEstimate

__all__ = ["InitStage", "init_views", "biplane_init"]


@dataclass(frozen=True)
class InitStage:
    """Each view's calibrated Init (``views``), the patient pose ``(4, 4)`` each implies (``implied``),
    their fusion (``patient_pose``) and how far apart (mm) they put the isocentre along the axis both
    views see (``view_disagreement_mm``)."""

    views: Mapping[str, InitEstimate]
    implied: Mapping[str, np.ndarray]
    patient_pose: np.ndarray
    view_disagreement_mm: float


def init_views(case: PreparedCase, init: InitPredictor, calibration: Calibration, *, fix_side: bool,
               monitor: Monitor) -> dict[str, InitEstimate]:
    """Calibrated Init of each view's MAP; ``fix_side``: the lateral side from the acquisition angle
    (else the network's own reading)."""
    estimates = {}
    for i, key in enumerate(VIEW_KEYS):
        monitor.step("init", i / 2, f"Init {key.upper()}")
        view = case.views[key].view_label if fix_side else None
        estimates[key] = calibrated_init(case.model_target(key), key == "lat", init, calibration, view=view)
    return estimates


def biplane_init(case: PreparedCase, init: InitPredictor, calibration: Calibration, rig: Mapping[str, np.ndarray],
                 monitor: Monitor) -> InitStage:
    """Init of both views fused into one patient pose (``rig``: each arm's ``A_v``)."""
    estimates = init_views(case, init, calibration, fix_side=True, monitor=monitor)
    implied = {key: patient_pose(estimates[key].pose_native, rig[key]) for key in VIEW_KEYS}
    return InitStage(estimates, implied, fuse_patient_poses(implied, rig), axis_disagreement_mm(implied, rig))
