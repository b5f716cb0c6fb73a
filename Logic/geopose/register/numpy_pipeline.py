"""The registration without PyTorch: calibration, calibrated Init and similarity-gated
Refine (paper sections 2.3.1-2.3.2) on the numpy renderer and onnxruntime networks.

This is what the Slicer module runs when PyTorch is not installed. It follows
``pipeline.py`` stage by stage with the numpy twins of the renderer, the pose
algebra and mNCC; test-time optimisation needs gradients and so needs torch. DRRs
for the networks are rendered at ``render_px`` and resized bilinearly to the
256-px model detector, as the shipped models were trained. Results are the same
dataclasses as the torch pipeline's, holding numpy arrays.
"""

from __future__ import annotations

import os
import time
from typing import Mapping

import numpy as np

from .. import contract as C
from ..dsa import DSARun, PreparedDSA
from ..geometry.detector import Detector
from ..geometry.numpy_poses import invert, isopose
from ..metrics.numpy_similarity import mncc
from ..nets.onnx_runtime import OnnxInit, OnnxRefine, onnx_predictors
from ..nets.preprocess import normalize_minmax
from ..render.numpy_drr import NumpyDRR
from ..resources import default_models_dir
from ..volume import Volume
from .case import (
    CRANIUM_CHANNEL, LABEL_GROUPS, TTO_PX_CPU, VIEW_KEYS, case_labels, check_view_keys, prepare_views, silhouette_dice,
)
from .gating import gated_refinement
from .progress import CancelCheck, Monitor, ProgressCallback
from .quality import assess
from .results import Calibration, CaseRegistration, InitEstimate, RefineTrace, RegistrationOptions, ViewOutcome

__all__ = ["DEFAULT_RENDER_PX", "DEVICE_LABEL", "register_case_numpy", "render_model_view", "greedy_refine_numpy"]

#: Pixels of the DRRs the networks see, before resizing to the model detector.
DEFAULT_RENDER_PX = 128
#: What the result record names as the device of this path.
DEVICE_LABEL = "cpu (numpy renderer, onnxruntime)"


def render_model_view(drr: NumpyDRR, pose: np.ndarray, render_px: int = DEFAULT_RENDER_PX) -> np.ndarray:
    """Min-max DRR (total channel) in the model geometry K0: ``(1, 1, 256, 256)``."""
    return normalize_minmax(drr(pose, detector=Detector.model(), channels=(0,), render_px=render_px)[None])


def greedy_refine_numpy(
    drr: NumpyDRR,
    target: np.ndarray,
    pose: np.ndarray,
    view: int,
    refine: OnnxRefine,
    max_proposals: int = C.GREEDY_MAX_PROPOSALS,
    render_px: int = DEFAULT_RENDER_PX,
    monitor: Monitor | None = None,
) -> RefineTrace:
    """Refine ``pose`` ``(4, 4)`` against a model-geometry ``target`` ``(1, 1, 256, 256)``
    (the rule of ``gating.py``; proposals ``inverse(D) @ T``)."""
    return gated_refinement(
        pose,
        lambda p: render_model_view(drr, p, render_px),
        lambda image: mncc(target[0, 0], image[0, 0]),
        lambda current, image: invert(refine.predict_residual(target, image, view)[0]) @ current,
        max_proposals,
        monitor,
    )


def _final_scores(drr: NumpyDRR, pose: np.ndarray, prepared: PreparedDSA) -> tuple[float, float]:
    """(mNCC of the DRR against the TTO target, hard Dice of the projected cranium and the DSA mask)."""
    image = drr(pose, detector=prepared.tto_detector, channels=(0, CRANIUM_CHANNEL))
    return mncc(prepared.tto_image, image[0]), silhouette_dice(image[1], prepared.tto_mask)


def register_case_numpy(
    cta: Volume,
    dsa: Mapping[str, DSARun],
    *,
    models: str | os.PathLike | Mapping[str, str | os.PathLike] | tuple[OnnxInit, OnnxRefine] | None = None,
    cranium_mask: Volume | None = None,
    segmentation: Volume | None = None,
    dsa_masks: Mapping[str, np.ndarray] | None = None,
    refine_steps: int = C.GREEDY_MAX_PROPOSALS,
    render_px: int = DEFAULT_RENDER_PX,
    tto_px: int = TTO_PX_CPU,
    model_clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES,
    progress: ProgressCallback | None = None,
    cancel: CancelCheck | None = None,
) -> CaseRegistration:
    """Register a native CTA (HU) to ``dsa = {"pa": run, "lat": run}`` with Init + greedy Refine.

    ``models``: a model folder whose manifest lists ONNX graphs (default: the shipped
    models), ``{"init": graph, "refine": graph}``, or runners from ``onnx_predictors``.
    ``tto_px`` sizes the acquisition-geometry image on which the final mNCC and the
    silhouette Dice are scored; ``model_clip_percentiles`` as in :class:`RegistrationOptions`.
    Every pose is ``(1, 4, 4)`` camera-to-centred-native (mm).
    """
    options = RegistrationOptions(refine_steps=refine_steps, iterations=0, tto_px=tto_px, device="cpu",
                                  model_clip_percentiles=model_clip_percentiles)
    monitor = Monitor(progress, cancel)
    times: dict[str, float] = {}
    if isinstance(models, tuple):
        init, refine = models
    else:
        init, refine = onnx_predictors(default_models_dir() if models is None else models)

    check_view_keys(dsa)
    t0 = time.perf_counter()
    monitor.step("prepare", 0.0, "CTA masks")
    labels, labels_source = case_labels(cta, cranium_mask, segmentation)
    drr = NumpyDRR.from_volume(cta, Detector.model(), labels=labels, label_groups=LABEL_GROUPS)
    prepared = prepare_views(dsa, tto_px=tto_px, dsa_masks=dsa_masks, monitor=monitor,
                             model_clip_percentiles=options.model_clip_percentiles)
    times["prepare"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    monitor.step("calibration", 0.0, "rendering the PA calibration DRR")
    t_cal = isopose(C.VIEW_PA)
    image = render_model_view(drr, t_cal, render_px)
    predicted = init.predict(image, is_lateral=False)[0][0]
    calibration = Calibration(t_cal[None], predicted[None], (t_cal @ invert(predicted))[None], image)
    times["calibration"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    inits = {}
    targets = {key: prepared[key].model_image[None, None].astype(np.float32) for key in VIEW_KEYS}
    for i, key in enumerate(VIEW_KEYS):
        monitor.step("init", i / 2, f"Init {key.upper()}")
        pose, view, logits = init.predict(targets[key], is_lateral=key == "lat")
        inits[key] = InitEstimate(calibration.to_native(pose), pose, int(view[0]), logits)
    times["init"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    refined = {
        key: greedy_refine_numpy(
            drr, targets[key], inits[key].pose_native[0], inits[key].view, refine, refine_steps, render_px, monitor
        )
        for key in VIEW_KEYS
    }
    times["refine"] = time.perf_counter() - t0

    outcomes = {}
    for key in VIEW_KEYS:
        final = refined[key].pose[None]
        score, dice = _final_scores(drr, final[0], prepared[key])
        outcomes[key] = ViewOutcome(key, prepared[key], inits[key], refined[key], final, score, dice, assess(score, dice, 0.0, 0.0))
    times["total"] = sum(times.values())
    monitor.step("done", 1.0, "registration finished (no test-time optimisation: it needs PyTorch)")
    return CaseRegistration(cta, labels, labels_source, calibration, outcomes, None, times, DEVICE_LABEL, options, drr)
