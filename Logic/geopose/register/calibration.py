"""Projection-space calibration and calibrated GeoPose-Init (paper section 2.3.1).

One DRR of the native CTA at the PA isopose, one Init pass decoded as PA, and
``A = T_iso_PA @ inverse(T_cal)`` moves canonical predictions into the native
frame: ``T_native = A @ T_pred`` (docs/conventions.md section 1). numpy poses; any
renderer and Init predictor.
"""

from __future__ import annotations

import numpy as np

from .. import contract as C
from ..geometry.detector import Detector
from ..geometry.poses import invert, isopose
from ..images import normalize_minmax
from ..nets.decoding import select_view
from ..nets.predictors import InitPredictor
from ..render.renderer import Renderer
from .progress import Monitor
from .results import Calibration, InitEstimate

__all__ = ["render_model_view", "calibrate", "calibrated_init"]


def render_model_view(renderer: Renderer, pose: np.ndarray, render_px: int) -> np.ndarray:
    """Min-max DRR (total channel) in the model geometry K0, rendered at ``render_px`` and
    resized to 256 x 256 as the networks were trained: ``(1, 1, 256, 256)`` float32."""
    image = renderer.render(pose, Detector.model(), ("total",), render_px=render_px)
    return normalize_minmax(image[None])


def calibrate(renderer: Renderer, init: InitPredictor, render_px: int, monitor: Monitor | None = None) -> Calibration:
    """Render the native CTA at the PA isopose and read Init's canonical pose for it."""
    (monitor or Monitor()).step("calibration", 0.0, "rendering the PA calibration DRR")
    t_cal = isopose(C.VIEW_PA)
    image = render_model_view(renderer, t_cal, render_px)
    predicted = init.predict(image, is_lateral=False)[0][0]
    return Calibration(t_cal, predicted, t_cal @ invert(predicted), image)


def calibrated_init(
    target: np.ndarray, is_lateral: bool, init: InitPredictor, calibration: Calibration, view: int | None = None
) -> InitEstimate:
    """Init on a preprocessed model-geometry target ``(1, 1, 256, 256)`` -> native pose. The view
    label is the network's (PA/lateral from ``is_lateral``, the side from the logits) unless
    ``view`` fixes it (the biplane registration takes the side from the acquisition geometry)."""
    pose, label, logits = init.predict(target, is_lateral=bool(is_lateral), view=view)
    network_view = int(select_view(logits, bool(is_lateral))[0])
    return InitEstimate(calibration.to_native(pose[0]), pose[0], int(label[0]), logits[0], network_view)
