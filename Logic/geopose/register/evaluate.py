"""Accuracy of registered poses against ground truth (phantom cases): mPCD, clDice and
pose errors per view and stage (numpy; renders with the case's renderer)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..dsa import DSARun
from ..errors import InputError
from ..jsonio import read_json
from ..volume import Volume
from ..geometry.detector import Detector
from ..geometry.poses import project_points
from ..metrics import MPCD, cldice, mpcd, pose_error_components, pose_errors
from ..render.renderer import Renderer
from .results import CaseRegistration

__all__ = ["Truth", "load_truth", "truth_for", "carotid_mpcd", "evaluate_pose", "truth_metrics", "vessel_mask", "VESSEL_MASK_FRACTION",
           "SUCCESS_MPCD_MM"]

#: A projected vessel pixel is one above this fraction of the image's maximum vessel line integral.
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
    #: The CTA grid the truth was made for: (shape ijk, ijk -> RAS 4 x 4).
    grid: tuple[tuple[int, ...], np.ndarray] | None = None


def load_truth(cta_path: str | Path) -> Truth | None:
    """``truth.json`` + ``centerlines.json`` next to a phantom CTA, or ``None`` if either is absent; content that
    is not a ``geopose phantom`` case's (missing keys, wrong shapes) is an :class:`InputError`."""
    folder = Path(cta_path).resolve().parent
    truth_file, lines_file = folder / "truth.json", folder / "centerlines.json"
    if not truth_file.exists() or not lines_file.exists():
        return None
    remedy = "it is not a geopose phantom's; move it away from the CTA (it only adds accuracy metrics)"
    truth, lines = read_json(truth_file, remedy), read_json(lines_file, remedy)
    try:
        poses = {key: np.asarray(truth["views"][key]["pose_camera_to_world"], float) for key in ("pa", "lat")}
        carotid_labels = {int(v) for name, v in truth["labels"].items() if name.startswith("ica")}
        carotid = [np.asarray(c["points_mm"], float).reshape(-1, 3) for c in lines["centerlines"] if int(c["label"]) in carotid_labels]
        grid = (tuple(int(n) for n in truth["shape_ijk"]), np.asarray(truth["ijk_to_ras"], float))
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise InputError(f"{truth_file} has no readable {exc} where a phantom case's truth has one; {remedy}") from None
    if any(p.shape != (4, 4) or not np.isfinite(p).all() for p in poses.values()) or grid[1].shape != (4, 4):
        raise InputError(f"{truth_file} holds poses or a grid that are not 4 x 4 matrices; {remedy}")
    if not carotid:
        raise InputError(f"{lines_file} holds no internal carotid centreline; {remedy}")
    return Truth(poses, np.concatenate(carotid), str(truth_file), grid)


def truth_for(cta_path: str | Path, cta: Volume) -> tuple[Truth | None, str | None]:
    """The phantom truth beside ``cta_path`` if it describes ``cta`` (its grid and affine), else ``None``; and a
    note when a truth file was there but is not used."""
    try:
        truth = load_truth(cta_path)
    except InputError as exc:
        return None, f"ground truth ignored, no accuracy metrics: {exc}"
    if truth is None:
        return None, None
    shape, affine = truth.grid
    if shape != tuple(cta.shape_ijk) or not np.allclose(affine, cta.ijk_to_ras, atol=1e-3):
        return None, (f"ground truth ignored, no accuracy metrics: {truth.source} describes a {shape} grid with another "
                      "affine than this CTA's, so it belongs to another case")
    return truth, None


def vessel_mask(image: np.ndarray, reference_max: float | None = None) -> np.ndarray:
    """Projected vessel mask of a vessel-channel image: pixels above ``VESSEL_MASK_FRACTION`` of
    ``reference_max`` (default: the image's own maximum). The one threshold of the project."""
    top = float(np.max(image)) if reference_max is None else float(reference_max)
    return np.asarray(image) > VESSEL_MASK_FRACTION * top if top > 0 else np.zeros(np.shape(image), dtype=bool)


def carotid_mpcd(
    poses: np.ndarray, true_pose: np.ndarray, detector: Detector, sod_mm: float, carotid_points_mm: np.ndarray
) -> list[MPCD]:
    """mPCD of estimated poses ``(B, 4, 4)`` (or one ``(4, 4)``) against ``true_pose``: the carotid
    points projected with both, the true projection being the reference centreline."""
    est = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    p_est, _ = project_points(est, detector, carotid_points_mm)
    p_ref, _ = project_points(np.asarray(true_pose, dtype=np.float64), detector, carotid_points_mm)
    return [mpcd(p, p_ref, detector.spacing_mm, sod_mm, detector.sdd_mm) for p in p_est]


def evaluate_pose(
    pose: np.ndarray,
    true_pose: np.ndarray,
    detector: Detector,
    sod_mm: float,
    carotid_points_mm: np.ndarray | None,
    renderer: Renderer | None = None,
    mask_detector: Detector | None = None,
) -> dict:
    """Metrics of one estimated pose ``(4, 4)`` against the truth on ``detector``.

    Pose errors always (also split into in-plane, depth and out-of-plane parts); mPCD when carotid points are given (:func:`carotid_mpcd`); clDice of the
    projected vessel masks rendered on ``mask_detector`` when a renderer is given.
    """
    est, ref = np.asarray(pose, dtype=np.float64).reshape(4, 4), np.asarray(true_pose, dtype=np.float64).reshape(4, 4)
    err = pose_errors(est[None], ref[None], sdd_mm=detector.sdd_mm)
    out = {
        "rotation_error_deg": float(err.rotation_deg[0]),
        "euler_error_deg": err.euler_deg[0].tolist(),
        "translation_error_mm": err.translation_mm[0].tolist(),
        "translation_error_norm_mm": float(err.translation_norm_mm[0]),
        "source_distance_mm": float(err.source_distance_mm[0]),
        "double_geodesic_mm": float(err.double_geodesic_mm[0]),
        **pose_error_components(est, ref),
    }
    if carotid_points_mm is not None:
        d = carotid_mpcd(est, ref, detector, sod_mm, carotid_points_mm)[0]
        out |= {"mpcd_px": d.px, "mpcd_mm": d.detector_mm, "mpcd_isocentre_mm": d.isocentre_mm,
                "success": d.detector_mm < SUCCESS_MPCD_MM}
    if renderer is not None:
        det = mask_detector or detector
        images = renderer.render(np.stack((ref, est)), det, ("vessels",))[:, 0]
        ref_mask = vessel_mask(images[0])
        est_mask = vessel_mask(images[1], float(images[0].max()))
        out["cldice"] = cldice(est_mask, ref_mask) if ref_mask.any() else None
    return out


def truth_metrics(case: CaseRegistration, runs: dict[str, DSARun], truth: Truth) -> dict[str, dict]:
    """``{view: {stage: metrics}}`` against the phantom truth (see :func:`evaluate_pose`)."""
    return {
        key: {
            stage: evaluate_pose(pose, truth.poses[key], runs[key].detector, runs[key].angles.sod_mm, truth.carotid_points_mm,
                                 renderer=case.renderer, mask_detector=view.prepared.tto_detector)
            for stage, pose in view.stage_poses.items()
        }
        for key, view in case.views.items()
    }
