"""Accuracy of registered poses against ground truth (phantom cases): mPCD,
clDice and pose errors per view and stage."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..dsa import DSARun
from ..geometry import Detector, project_points
from ..metrics import cldice, mpcd, pose_errors
from ..render import DRR
from .case import VESSEL_CHANNEL
from .results import CaseRegistration

__all__ = ["Truth", "load_truth", "carotid_mpcd", "evaluate_pose", "truth_metrics", "VESSEL_MASK_FRACTION", "SUCCESS_MPCD_MM"]

#: A projected vessel pixel is one above this fraction of the reference image's maximum.
VESSEL_MASK_FRACTION = 0.05
#: A registration counts as a success below this mPCD (mm at the detector), as in the paper.
SUCCESS_MPCD_MM = 5.0


@dataclass
class Truth:
    """True poses ``{"pa", "lat"} -> (4, 4)`` (camera-to-centred-native, mm) and the
    carotid centreline points ``(N, 3)`` in the centred native frame (mm)."""

    poses: dict[str, np.ndarray]
    carotid_points_mm: np.ndarray
    source: str = ""


def load_truth(cta_path: str | Path) -> Truth | None:
    """``truth.json`` + ``centerlines.json`` next to a phantom CTA, or ``None`` if absent."""
    folder = Path(cta_path).resolve().parent
    truth_file, lines_file = folder / "truth.json", folder / "centerlines.json"
    if not truth_file.is_file() or not lines_file.is_file():
        return None
    truth = json.loads(truth_file.read_text())
    lines = json.loads(lines_file.read_text())["centerlines"]
    poses = {key: np.asarray(truth["views"][key]["pose_camera_to_world"], float) for key in ("pa", "lat")}
    carotid_labels = {int(v) for name, v in truth["labels"].items() if name.startswith("ica")}
    carotid = [np.asarray(c["points_mm"], float) for c in lines if int(c["label"]) in carotid_labels]
    if not carotid:
        raise ValueError(f"{lines_file} holds no internal carotid centreline")
    return Truth(poses, np.concatenate(carotid), str(truth_file))


def _vessel_mask(drr: DRR, pose: torch.Tensor, detector: Detector, channel: int, threshold: float) -> np.ndarray:
    with torch.no_grad():
        img = drr(pose.to(drr.density.device, torch.float32), detector=detector, channels=(channel,))[0, 0]
    return (img > threshold).cpu().numpy()


def carotid_mpcd(
    poses: torch.Tensor, true_pose: torch.Tensor, detector: Detector, sod_mm: float, carotid_points_mm: np.ndarray
) -> list:
    """mPCD (``geopose.metrics.MPCD`` each) of estimated poses ``(B, 4, 4)`` against ``true_pose``:
    the carotid points projected with both, the true projection being the reference centreline."""
    est = torch.as_tensor(poses, dtype=torch.float64).reshape(-1, 4, 4).cpu()
    ref = torch.as_tensor(true_pose, dtype=torch.float64).reshape(1, 4, 4).cpu()
    pts = torch.as_tensor(carotid_points_mm, dtype=torch.float64)
    p_est, _ = project_points(est, detector, pts)
    p_ref, _ = project_points(ref, detector, pts)
    return [mpcd(p.numpy(), p_ref[0].numpy(), detector.spacing_mm, sod_mm, detector.sdd_mm) for p in p_est]


def evaluate_pose(
    pose: torch.Tensor,
    true_pose: torch.Tensor,
    detector: Detector,
    sod_mm: float,
    carotid_points_mm: np.ndarray | None,
    drr: DRR | None = None,
    vessel_channel: int | None = None,
    mask_detector: Detector | None = None,
) -> dict:
    """Metrics of one estimated pose ``(1, 4, 4)`` against the truth on ``detector``.

    Pose errors always; mPCD when carotid points are given (:func:`carotid_mpcd`);
    clDice compares projected vessel masks rendered on ``mask_detector`` (when a
    renderer with a vessel channel is given).
    """
    est = torch.as_tensor(pose, dtype=torch.float64).reshape(1, 4, 4).cpu()
    ref = torch.as_tensor(true_pose, dtype=torch.float64).reshape(1, 4, 4).cpu()
    err = pose_errors(est, ref, sdd_mm=detector.sdd_mm)
    out = {
        "rotation_error_deg": float(err.rotation_deg[0]),
        "euler_error_deg": err.euler_deg[0].tolist(),
        "translation_error_mm": err.translation_mm[0].tolist(),
        "translation_error_norm_mm": float(err.translation_norm_mm[0]),
        "source_distance_mm": float(err.source_distance_mm[0]),
        "double_geodesic_mm": float(err.double_geodesic_mm[0]),
    }
    if carotid_points_mm is not None:
        d = carotid_mpcd(est, ref, detector, sod_mm, carotid_points_mm)[0]
        out |= {"mpcd_px": d.px, "mpcd_mm": d.detector_mm, "mpcd_isocentre_mm": d.isocentre_mm,
                "success": d.detector_mm < SUCCESS_MPCD_MM}
    if drr is not None and vessel_channel is not None:
        det = mask_detector or detector
        with torch.no_grad():
            ref_img = drr(ref.to(drr.density.device, torch.float32), detector=det, channels=(vessel_channel,))[0, 0]
        threshold = VESSEL_MASK_FRACTION * float(ref_img.max())
        ref_mask = (ref_img > threshold).cpu().numpy()
        est_mask = _vessel_mask(drr, est, det, vessel_channel, threshold)
        out["cldice"] = cldice(est_mask, ref_mask) if ref_mask.any() else None
    return out


def truth_metrics(case: CaseRegistration, runs: dict[str, DSARun], truth: Truth) -> dict[str, dict]:
    """``{view: {stage: metrics}}`` against the phantom truth (see :func:`evaluate_pose`)."""
    out = {}
    for key, view in case.views.items():
        true_pose = torch.as_tensor(truth.poses[key], dtype=torch.float64)
        run = runs[key]
        out[key] = {
            stage: evaluate_pose(
                pose, true_pose, run.detector, run.angles.sod_mm, truth.carotid_points_mm,
                drr=case.drr, vessel_channel=VESSEL_CHANNEL, mask_detector=view.prepared.tto_detector,
            )
            for stage, pose in view.stage_poses.items()
        }
    return out
