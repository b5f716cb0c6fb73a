"""The whole GeoPose registration of one case: calibration, calibrated Init,
gated refinement and test-time optimisation for a PA + lateral DSA pair.

``register_case`` is the keyword API used by the CLI, the demo and Slicer; each
stage it calls is usable on its own (``calibration``, ``refine``, ``tto``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import torch

from .. import contract as C
from ..cta import cranium_mask_from_cta, vessel_mask_from_cta
from ..dsa import LAT_ROLE, PA_ROLE, DSARun, PreparedDSA, preprocess_dsa
from ..geometry import Detector, RigidTransform, rotation_angle_rad
from ..metrics import mncc
from ..nets import InitPredictor, RefinePredictor
from ..render import DRR
from ..volume import Volume
from .calibration import Calibration, InitEstimate, calibrate, calibrated_init
from .progress import CancelCheck, Monitor, ProgressCallback
from .quality import Quality, assess
from .refine import RefineTrace, greedy_refine
from .tto import TTOResult, TTOView, test_time_optimise

__all__ = [
    "RegistrationOptions", "ViewOutcome", "CaseRegistration", "PreparedCase", "prepare_case", "register_case",
    "final_mncc", "resolve_device", "case_labels", "synchronize",
]

#: Label values of the combined CTA label map handed to the renderer.
CRANIUM_BIT = 1
VESSEL_BIT = 2
LABEL_GROUPS = {"cranium": [CRANIUM_BIT, CRANIUM_BIT | VESSEL_BIT], "vessels": [VESSEL_BIT, CRANIUM_BIT | VESSEL_BIT]}
CRANIUM_CHANNEL = 1
VESSEL_CHANNEL = 2
VIEW_KEYS = ("pa", "lat")
#: Default TTO image size (pixels along the detector's longer side): the GPU affords
#: the model resolution; on a CPU half of it keeps a registration under a minute.
TTO_PX_CUDA = 256
TTO_PX_CPU = 128


@dataclass
class RegistrationOptions:
    """Knobs of :func:`register_case` (defaults follow the paper)."""

    refine_steps: int = C.GREEDY_MAX_PROPOSALS
    iterations: int = C.TTO_ITERATIONS
    tto_px: int | None = None  # None: TTO_PX_CUDA on a GPU, TTO_PX_CPU on a CPU
    biplanar: bool = False
    device: str = "auto"


@dataclass
class ViewOutcome:
    """Everything one view went through; poses ``(1, 4, 4)`` camera-to-centred-native (mm)."""

    key: str
    prepared: PreparedDSA
    init: InitEstimate
    refine: RefineTrace
    final_pose: torch.Tensor
    final_mncc: float
    silhouette_dice: float
    quality: Quality

    @property
    def stage_poses(self) -> dict[str, torch.Tensor]:
        return {"init": self.init.pose_native, "refine": self.refine.pose, "final": self.final_pose}


@dataclass
class CaseRegistration:
    """The in-memory result of :func:`register_case` (``record.py`` turns it into JSON)."""

    cta: Volume
    labels: Volume
    labels_source: dict
    calibration: Calibration
    views: dict[str, ViewOutcome]
    tto: TTOResult | None
    runtimes_s: dict[str, float]
    device: str
    options: RegistrationOptions
    drr: DRR = field(repr=False)


def resolve_device(device: str) -> torch.device:
    """``auto`` takes CUDA when present; ``cuda`` without a GPU is a clear error."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but no CUDA device is available: use --device cpu or auto")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {device!r}")
    return torch.device(device)


def case_labels(cta: Volume, cranium_mask: Volume | None, segmentation: Volume | None) -> tuple[Volume, dict]:
    """Combined label map (cranium bit 1, vessel bit 2) on the CTA grid, and where each part came from.

    Missing parts are computed from the CTA (``geopose.cta.masks``); the vessel
    part is then a contrast-threshold approximation and the record says so.
    """
    source = {}
    for name, vol in (("cranium mask", cranium_mask), ("segmentation", segmentation)):
        if vol is not None and vol.array.shape != cta.array.shape:
            raise ValueError(
                f"the {name} grid {vol.shape_ijk} differs from the CTA grid {cta.shape_ijk}: resample it onto the CTA first"
            )
    if cranium_mask is None:
        cranium_mask = cranium_mask_from_cta(cta)
        source["cranium"] = "computed from the CTA (bone threshold, largest component, filled)"
    else:
        source["cranium"] = "given"
    if segmentation is None:
        vessels = vessel_mask_from_cta(cta, cranium_mask).array > 0
        source["vessels"] = "contrast-threshold vessel mask inside the cranium (no segmentation given)"
    else:
        vessels = segmentation.array > 0
        source["vessels"] = "given segmentation"
    combined = (cranium_mask.array > 0).astype(np.uint8) * CRANIUM_BIT + vessels.astype(np.uint8) * VESSEL_BIT
    return cta.like(combined, role="geopose case labels"), source


def _tensor(image: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(image), dtype=torch.float32, device=device)[None, None]


def silhouette_dice(drr: DRR, pose: torch.Tensor, prepared: PreparedDSA) -> float:
    """Hard Dice between the projected CTA cranium (channel > 0) and the DSA cranium mask (TTO geometry)."""
    with torch.no_grad():
        sil = drr(pose, detector=prepared.tto_detector, channels=(CRANIUM_CHANNEL,))[0, 0] > 0
    ref = torch.as_tensor(prepared.tto_mask > 0, device=sil.device)
    denom = int(sil.sum()) + int(ref.sum())
    return 1.0 if denom == 0 else 2.0 * int((sil & ref).sum()) / denom


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
    if set(dsa) != set(VIEW_KEYS):
        raise ValueError(f"need one PA and one lateral DSA run as {{'pa': ..., 'lat': ...}}, got {sorted(dsa)}")
    device = resolve_device(options.device)
    monitor.step("prepare", 0.0, "CTA masks")
    labels, labels_source = case_labels(cta, cranium_mask, segmentation)
    drr = DRR.from_volume(cta, Detector.model(), labels=labels, label_groups=LABEL_GROUPS, device=device)
    prepared: dict[str, PreparedDSA] = {}
    for i, key in enumerate(VIEW_KEYS):
        monitor.step("prepare", (i + 1) / 3, f"DSA {key.upper()}")
        kwargs = {"mask": dsa_masks[key]} if dsa_masks and key in dsa_masks else {}
        kwargs["tto_px"] = options.tto_px or (TTO_PX_CUDA if device.type == "cuda" else TTO_PX_CPU)
        prepared[key] = preprocess_dsa(dsa[key], **kwargs)
    if prepared["pa"].view_role != PA_ROLE or prepared["lat"].view_role != LAT_ROLE:
        raise ValueError(
            f"the 'pa' run looks {prepared['pa'].view_role} and the 'lat' run {prepared['lat'].view_role} by their "
            "primary angles: swap them, or override the angle (primary_deg) if the tags are wrong"
        )
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
        return float(mncc(_tensor(prepared.tto_image, device), image))


def synchronize(device: torch.device) -> None:
    """Wait for queued CUDA work, so a timing boundary measures it (no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
