"""Projection-space calibration and calibrated GeoPose-Init (paper section 2.3.1).

One DRR of the native CTA at the PA isopose, one Init pass decoded as PA, and
``A = T_iso_PA @ inverse(T_cal)`` moves canonical predictions into the native
frame: ``T_native = A @ T_pred``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .. import contract as C
from ..geometry import Detector, RigidTransform, isopose
from ..nets import InitPredictor, normalize_minmax
from ..render import DRR
from .results import Calibration, InitEstimate

__all__ = ["calibrate", "calibrated_init", "render_model_view"]


def render_model_view(drr: DRR, pose: Tensor) -> Tensor:
    """Min-max DRR (total channel) in the model geometry K0: ``(B, 1, 256, 256)``."""
    return normalize_minmax(drr(pose, detector=Detector.model(), channels=(0,)))


@torch.no_grad()
def calibrate(drr: DRR, init: InitPredictor) -> Calibration:
    """Render the native CTA at the PA isopose and read Init's canonical pose for it."""
    dev = drr.density.device
    t_cal = isopose(C.VIEW_PA, device=dev).matrix
    image = render_model_view(drr, t_cal)
    predicted, _, _ = init.predict(image, is_lateral=torch.tensor([False], device=dev))
    predicted = predicted.to(t_cal.dtype)
    transfer = t_cal @ RigidTransform(predicted).inverse().matrix
    return Calibration(t_cal, predicted, transfer, image)


@torch.no_grad()
def calibrated_init(target: Tensor, is_lateral: bool, init: InitPredictor, calibration: Calibration) -> InitEstimate:
    """Init on a preprocessed model-geometry target ``(1, 1, 256, 256)`` -> native pose."""
    lateral = torch.tensor([bool(is_lateral)], device=target.device)
    pose, view, logits = init.predict(normalize_minmax(target), is_lateral=lateral)
    pose = pose.to(calibration.frame_transfer.dtype)
    return InitEstimate(calibration.to_native(pose), pose, int(view[0]), logits)
