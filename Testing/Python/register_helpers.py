"""Helpers of the registration stages' tests (test_pipeline.py, test_tto.py, test_refine.py, ...):
oracle Init and Refine predictors that answer ground truth in place of trained networks, the
phantom case read back through the real file formats, a world-frame perturbation, and a PA +
lateral biplane rig with the patient poses and rotations its tests build."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from geopose import contract as C
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.geometry import pose_from_params
from geopose.geometry.detector import AP_REORIENT, CArmAngles
from geopose.geometry.poses import pose_from_carm_angles
from geopose.phantom import labels as L
from geopose.register import prepare_case
from geopose.register.evaluate import load_truth
from geopose.render.renderer import TorchRenderer


#: Network-input render size of the oracle "models".
ORACLE_RENDER_PX = 64


class OracleInit:
    """Answers queued canonical poses in call order (the view label from metadata)."""

    def __init__(self, answers: list[np.ndarray]):
        self.answers = list(answers)
        self.images: list[np.ndarray] = []

    def predict(self, image, is_lateral=None, mirror=True, view=None):
        self.images.append(image)
        pose = np.asarray(self.answers.pop(0), dtype=np.float64).reshape(1, 4, 4)
        if view is None:
            view = C.VIEW_LAT_PLUS if bool(np.asarray(is_lateral).reshape(-1)[0]) else C.VIEW_PA
        view = np.array([view]).reshape(1)
        return pose, view, np.eye(3)[view]


class OracleRefine:
    """Answers queued residuals ``D`` in order, one per image of a batch (identity once the queue is
    empty; the caller applies ``inverse(D) @ T``); ``answered`` counts them."""

    def __init__(self, residuals: list[np.ndarray]):
        self.residuals = list(residuals)
        self.answered = 0

    def predict_residual(self, target, render, view):
        self.answered += len(render)
        return np.stack([np.asarray(self.residuals.pop(0)).reshape(4, 4) if self.residuals else np.eye(4)
                         for _ in range(len(render))])


def _perturb(T: np.ndarray, rot_deg=(3.0, -3.0, 2.0), trans_mm=(6.0, -5.0, 6.0)) -> np.ndarray:
    """A world-frame perturbation: rotation ~4.7 deg about the centre, translation ~9.8 mm."""
    D = pose_from_params(np.radians(rot_deg), np.zeros(3))
    D[:3, 3] = trans_mm
    return D @ np.asarray(T, dtype=np.float64)


def _read_phantom(case: Path):
    """(native-to-canonical (4, 4), true camera-to-world poses per view, CTA, DSA runs) of a
    phantom folder written by ``geopose phantom``."""
    truth = json.loads((case / "truth.json").read_text())
    N = np.asarray(truth["native_to_canonical"], dtype=np.float64)
    true = {k: np.asarray(truth["views"][k]["pose_camera_to_world"]) for k in ("pa", "lat")}
    return N, true, load_cta(case / "cta.nii.gz"), {k: read_dsa(case / f"dsa_{k}.dcm") for k in ("pa", "lat")}


def _prepared(case: Path):
    """(truth, runs, prepared case, torch renderer) of the phantom case, its vessels segmented."""
    truth = load_truth(case / "cta.nii.gz")
    cta = load_cta(case / "cta.nii.gz")
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    runs = {k: read_dsa(case / f"dsa_{k}.dcm") for k in ("pa", "lat")}
    prep = prepare_case(cta, runs, segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)), tto_px=128)
    return truth, runs, prep, TorchRenderer(prep.volume)


SID_MM, SOD_MM = 1200.0, 800.0
#: A PA + lateral rig as the DICOM angles give it (slightly oblique, like real runs).
RIG = {
    "pa": pose_from_carm_angles(CArmAngles(3.0, -4.0, SID_MM, SOD_MM)),
    "lat": pose_from_carm_angles(CArmAngles(88.0, 2.0, SID_MM, SOD_MM)),
}


RENDER_PX = 64


def _patient(rot_deg=(2.0, -3.0, 1.5), shift_mm=(4.0, -6.0, 3.0)) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = pose_from_params(np.radians(rot_deg), np.zeros(3))[:3, :3]
    X[:3, 3] = shift_mm
    return X


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix of ``deg`` about the unit ``axis`` (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _ray(key: str, X: np.ndarray = np.eye(4)) -> np.ndarray:
    """The view's central-ray direction in the CTA frame."""
    return (X @ RIG[key] @ AP_REORIENT)[:3, 2]
