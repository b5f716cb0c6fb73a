"""The whole GeoPose registration of one case: calibration, calibrated Init,
gated refinement and test-time optimisation for a PA + lateral DSA pair.

``register_case`` is the keyword API used by the CLI, the demo and Slicer; each
stage it calls is usable on its own (``calibration``, ``refine``, ``tto``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch

from ..dsa import DSARun, PreparedDSA
from ..geometry import Detector, RigidTransform, rotation_angle_rad
from ..metrics import mncc
from ..nets import InitPredictor, RefinePredictor
from ..render import DRR
from ..volume import Volume
from .calibration import calibrate, calibrated_init
from .case import (
    CRANIUM_CHANNEL, LABEL_GROUPS, TTO_PX_CPU, TTO_PX_CUDA, VIEW_KEYS, case_labels, check_view_keys, prepare_views,
)
from .case import silhouette_dice as mask_dice
from .progress import CancelCheck, Monitor, ProgressCallback
from .quality import assess
from .refine import greedy_refine
from .results import CaseRegistration, RegistrationOptions, ViewOutcome
from .tto import TTOView, test_time_optimise

__all__ = ["PreparedCase", "prepare_case", "register_case", "final_mncc", "resolve_device", "synchronize"]


def resolve_device(device: str) -> torch.device:
    """``auto`` takes CUDA when present; ``cuda`` without a GPU is a clear error."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but no CUDA device is available: use --device cpu or auto")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {device!r}")
    return torch.device(device)


def _tensor(image: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(image), dtype=torch.float32, device=device)[None, None]


def silhouette_dice(drr: DRR, pose: torch.Tensor, prepared: PreparedDSA) -> float:
    """Hard Dice between the projected CTA cranium and the DSA cranium mask (TTO geometry)."""
    with torch.no_grad():
        silhouette = drr(pose, detector=prepared.tto_detector, channels=(CRANIUM_CHANNEL,))[0, 0]
    return mask_dice(silhouette.cpu().numpy(), prepared.tto_mask)


@dataclass
class PreparedCase:
    """A case ready for the stages: the combined CTA labels, the renderer on the
    chosen device, and each view's preprocessed DSA (``{"pa", "lat"}``)."""

    labels: Volume
    labels_source: dict
    drr: DRR
    views: dict[str, PreparedDSA]
    device: torch.device

    def model_target(self, key: str) -> torch.Tensor:
        """View ``key``'s model-geometry MAP ``(1, 1, 256, 256)`` on the case device."""
        return _tensor(self.views[key].model_image, self.device)

    def tto_target(self, key: str) -> torch.Tensor:
        """View ``key``'s MAP in its TTO geometry ``(1, 1, h, w)`` on the case device."""
        return _tensor(self.views[key].tto_image, self.device)

    def tto_view(self, key: str, pose: torch.Tensor) -> TTOView:
        """View ``key`` set up for :func:`test_time_optimise`, starting from ``pose`` ``(1, 4, 4)``."""
        p = self.views[key]
        return TTOView(key, self.tto_target(key), _tensor(p.tto_mask, self.device), p.tto_detector, pose.float())


def prepare_case(
    cta: Volume,
    dsa: Mapping[str, DSARun],
    *,
    cranium_mask: Volume | None = None,
    segmentation: Volume | None = None,
    dsa_masks: Mapping[str, np.ndarray] | None = None,
    options: RegistrationOptions | None = None,
    monitor: Monitor | None = None,
) -> PreparedCase:
    """CTA labels + renderer and the preprocessed PA / lateral runs (checked against their roles)."""
    options = options or RegistrationOptions()
    monitor = monitor or Monitor()
    check_view_keys(dsa)
    device = resolve_device(options.device)
    monitor.step("prepare", 0.0, "CTA masks")
    labels, labels_source = case_labels(cta, cranium_mask, segmentation)
    drr = DRR.from_volume(cta, Detector.model(), labels=labels, label_groups=LABEL_GROUPS, device=device)
    tto_px = options.tto_px or (TTO_PX_CUDA if device.type == "cuda" else TTO_PX_CPU)
    prepared = prepare_views(dsa, tto_px=tto_px, dsa_masks=dsa_masks, monitor=monitor,
                             model_clip_percentiles=options.model_clip_percentiles)
    return PreparedCase(labels, labels_source, drr, prepared, device)


def register_case(
    cta: Volume,
    dsa: Mapping[str, DSARun],
    *,
    init: InitPredictor,
    refine: RefinePredictor,
    cranium_mask: Volume | None = None,
    segmentation: Volume | None = None,
    dsa_masks: Mapping[str, np.ndarray] | None = None,
    options: RegistrationOptions | None = None,
    progress: ProgressCallback | None = None,
    cancel: CancelCheck | None = None,
) -> CaseRegistration:
    """Register a native CTA (HU) to ``dsa = {"pa": run, "lat": run}``.

    ``init`` / ``refine`` are predictors (``geopose.nets.make_predictors``) on the
    same device as ``options.device``. Returns every intermediate pose and trace.
    """
    options = options or RegistrationOptions()
    monitor = Monitor(progress, cancel)
    times: dict[str, float] = {}

    t0 = time.perf_counter()
    case = prepare_case(
        cta, dsa, cranium_mask=cranium_mask, segmentation=segmentation, dsa_masks=dsa_masks, options=options, monitor=monitor
    )
    device, drr, prepared = case.device, case.drr, case.views
    synchronize(device)
    times["prepare"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    monitor.step("calibration", 0.0, "rendering the PA calibration DRR")
    calibration = calibrate(drr, init)
    synchronize(device)
    times["calibration"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    inits = {}
    for i, key in enumerate(VIEW_KEYS):
        monitor.step("init", i / 2, f"Init {key.upper()}")
        inits[key] = calibrated_init(case.model_target(key), key == "lat", init, calibration)
    synchronize(device)
    times["init"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    refined = {
        key: greedy_refine(
            drr, case.model_target(key), inits[key].pose_native.float(), inits[key].view, refine, options.refine_steps,
            monitor=monitor,
        )
        for key in VIEW_KEYS
    }
    synchronize(device)
    times["refine"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    tto_result = None
    finals = {key: refined[key].pose for key in VIEW_KEYS}
    if options.iterations > 0:
        views = [case.tto_view(key, refined[key].pose) for key in VIEW_KEYS]
        tto_result = test_time_optimise(
            drr, views, options.iterations, cranium_channel=CRANIUM_CHANNEL, biplanar=options.biplanar, monitor=monitor
        )
        finals = dict(tto_result.poses)
    synchronize(device)
    times["tto"] = time.perf_counter() - t0

    outcomes = {}
    for key in VIEW_KEYS:
        p = prepared[key]
        score = final_mncc(drr, finals[key], p, device)
        dice = silhouette_dice(drr, finals[key], p)
        moved = RigidTransform(refined[key].pose.double()).inverse().matrix @ finals[key].double()
        rot = float(torch.rad2deg(rotation_angle_rad(moved[:, :3, :3]))[0])
        trans = float((finals[key][0, :3, 3].double() - refined[key].pose[0, :3, 3].double()).norm())
        outcomes[key] = ViewOutcome(key, p, inits[key], refined[key], finals[key], score, dice, assess(score, dice, rot, trans))
    times["total"] = sum(times.values())
    monitor.step("done", 1.0, "registration finished")
    return CaseRegistration(cta, case.labels, case.labels_source, calibration, outcomes, tto_result, times, str(device), options, drr)


def final_mncc(drr: DRR, pose: torch.Tensor, prepared: PreparedDSA, device: torch.device) -> float:
    """mNCC between the DSA MAP and the DRR at ``pose`` in the TTO geometry."""
    with torch.no_grad():
        image = drr(pose.float(), detector=prepared.tto_detector, channels=(0,))
        return float(mncc(_tensor(prepared.tto_image, device).double(), image.double()))


def synchronize(device: torch.device) -> None:
    """Wait for queued CUDA work, so a timing boundary measures it (no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
