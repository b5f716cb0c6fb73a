"""Registration and pose metrics (numpy): mPCD, clDice, pose errors, view accuracy.

Distances are in pixels (px) on the detector, millimetres at the detector (mm) or
at the isocentre (detector mm x SOD/SDD). Poses are camera-to-world ``(B, 4, 4)``
in the centred CTA frame (mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
import SimpleITK as sitk

from ..contract import MODEL_SDD_MM, VIEW_NAMES
from ..geometry.detector import AP_REORIENT
from ..geometry.poses import invert, matrix_to_axis_angle, params_from_pose, rotation_angle_rad

__all__ = [
    "MPCD",
    "mpcd",
    "mask_points",
    "skeletonize",
    "cldice",
    "PoseErrors",
    "pose_errors",
    "pose_error_components",
    "double_geodesic_mm",
    "view_accuracy",
]

# Distances are evaluated against the reference in chunks of this many query points.
_CDIST_CHUNK = 1024


# ------------------------------------------------------------- vessel metrics
@dataclass(frozen=True)
class MPCD:
    """Mean projected centreline distance: pixels, mm at the detector, mm at the isocentre."""

    px: float
    detector_mm: float
    isocentre_mm: float


def _as_points(name: str, points: ArrayLike) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must be (N, 2) (row, col) pixel coordinates, got shape {arr.shape}")
    if len(arr) == 0:
        raise ValueError(f"{name} is empty: no centreline points to measure")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains non-finite coordinates")
    return arr


def _nearest_distances(query: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance from each query point ``(N, 2)`` to its nearest reference point ``(M, 2)``."""
    out = [np.sqrt(((query[i : i + _CDIST_CHUNK, None] - reference[None]) ** 2).sum(-1).min(1))
           for i in range(0, len(query), _CDIST_CHUNK)]
    return np.concatenate(out)


def mpcd(
    projected_px: ArrayLike, reference_px: ArrayLike, spacing_mm: float | tuple[float, float], sod_mm: float, sdd_mm: float
) -> MPCD:
    """Mean distance from projected CTA centreline points to the nearest reference DSA centreline point.

    ``projected_px`` ``(N, 2)`` and ``reference_px`` ``(M, 2)`` are (row, col) pixels
    of the same detector; ``spacing_mm`` is its (row, col) pixel spacing (or one
    value); ``sod_mm``/``sdd_mm`` scale detector mm to the isocentre plane.
    """
    proj, ref = _as_points("projected_px", projected_px), _as_points("reference_px", reference_px)
    spacing = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (2,))
    if not (spacing > 0).all() or not 0 < sod_mm <= sdd_mm:
        raise ValueError(f"need positive pixel spacing and 0 < SOD <= SDD, got {spacing.tolist()}, {sod_mm}, {sdd_mm}")
    px = float(_nearest_distances(proj, ref).mean())
    mm = float(_nearest_distances(proj * spacing, ref * spacing).mean())
    return MPCD(px=px, detector_mm=mm, isocentre_mm=mm * sod_mm / sdd_mm)


def _as_mask(name: str, mask: ArrayLike) -> np.ndarray:
    arr = np.asarray(mask)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D mask, got shape {arr.shape}")
    return arr > 0


def mask_points(mask: ArrayLike) -> np.ndarray:
    """(row, col) pixel coordinates ``(N, 2)`` of the non-zero pixels of a 2-D mask."""
    return np.argwhere(_as_mask("mask", mask)).astype(np.float64)


def skeletonize(mask: ArrayLike) -> np.ndarray:
    """One-pixel-wide skeleton (bool, same shape) of a 2-D mask by morphological thinning."""
    image = sitk.GetImageFromArray(_as_mask("mask", mask).astype(np.uint8))
    return sitk.GetArrayFromImage(sitk.BinaryThinning(image)).astype(bool)


def cldice(pred_mask: ArrayLike, ref_mask: ArrayLike) -> float:
    """Centreline Dice (Shit et al. 2021) of two 2-D vessel masks, in [0, 1].

    ``2 Tprec Tsens / (Tprec + Tsens)`` with ``Tprec = |S(pred) & ref| / |S(pred)|``
    and ``Tsens = |S(ref) & pred| / |S(ref)|``, ``S`` the skeleton. An empty
    prediction scores 0; an empty reference is an error.
    """
    pred, ref = _as_mask("pred_mask", pred_mask), _as_mask("ref_mask", ref_mask)
    if pred.shape != ref.shape:
        raise ValueError(f"masks differ in shape: {pred.shape} vs {ref.shape}")
    skel_ref = skeletonize(ref)
    if not skel_ref.any():
        raise ValueError("the reference vessel mask is empty; clDice needs reference vessels")
    skel_pred = skeletonize(pred)
    if not skel_pred.any():
        return 0.0
    t_prec = (skel_pred & ref).sum() / skel_pred.sum()
    t_sens = (skel_ref & pred).sum() / skel_ref.sum()
    return 0.0 if t_prec + t_sens == 0 else float(2 * t_prec * t_sens / (t_prec + t_sens))


# ---------------------------------------------------------------- pose errors
def _as_poses(name: str, pose: ArrayLike) -> np.ndarray:
    m = np.asarray(pose, dtype=np.float64)
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must be (B, 4, 4) poses, got shape {m.shape}")
    return m.reshape(-1, 4, 4)


def double_geodesic_mm(pred: ArrayLike, ref: ArrayLike, sdd_mm: float = MODEL_SDD_MM) -> np.ndarray:
    """``sqrt((SDD/2 * angle)^2 + |c1 - c2|^2)`` (mm) ``(B,)``; ``c`` = source position (world, mm)."""
    a, b = _as_poses("pred", pred), _as_poses("ref", ref)
    angle = rotation_angle_rad(np.swapaxes(a[:, :3, :3], -1, -2) @ b[:, :3, :3])
    return np.sqrt((sdd_mm / 2.0 * angle) ** 2 + ((a[:, :3, 3] - b[:, :3, 3]) ** 2).sum(-1))


@dataclass(frozen=True)
class PoseErrors:
    """Per-item pose errors (pred - ref), float64 ``(B,)`` or ``(B, 3)``."""

    rotation_deg: np.ndarray  # geodesic angle of R_pred^T R_ref
    euler_deg: np.ndarray  # Euler ZYX (rz, ry, rx) differences wrapped to (-180, 180]
    translation_mm: np.ndarray  # rotated-frame t differences (GeoPose parameters)
    translation_norm_mm: np.ndarray
    source_distance_mm: np.ndarray  # distance between the X-ray source positions (world)
    double_geodesic_mm: np.ndarray


def pose_errors(pred: ArrayLike, ref: ArrayLike, sdd_mm: float = MODEL_SDD_MM) -> PoseErrors:
    """Errors of predicted poses against references (both ``(B, 4, 4)``)."""
    a, b = _as_poses("pred", pred), _as_poses("ref", ref)
    if a.shape != b.shape:
        raise ValueError(f"pred has {a.shape[0]} poses and ref {b.shape[0]}")
    (ra, ta), (rb, tb) = params_from_pose(a), params_from_pose(b)
    d_euler = np.remainder(ra - rb + math.pi, 2 * math.pi) - math.pi
    d_euler = np.where(d_euler <= -math.pi, d_euler + 2 * math.pi, d_euler)
    dt = ta - tb
    return PoseErrors(
        rotation_deg=np.degrees(rotation_angle_rad(np.swapaxes(a[:, :3, :3], -1, -2) @ b[:, :3, :3])),
        euler_deg=np.degrees(d_euler),
        translation_mm=dt,
        translation_norm_mm=np.linalg.norm(dt, axis=-1),
        source_distance_mm=np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=-1),
        double_geodesic_mm=double_geodesic_mm(a, b, sdd_mm),
    )


def pose_error_components(pred: ArrayLike, ref: ArrayLike) -> dict[str, float]:
    """One view's pose error split by what the view sees, in the true camera's frame: where the
    CTA centre (the world origin) lies in the two cameras, in the image plane and along the
    central ray (depth, mm), and the rotation error about the central ray (in-plane) and about
    the two image axes (out-of-plane, deg). Poses ``(4, 4)`` camera-to-world (AP reorientation
    included, as every pose of the project)."""
    a, b = _as_poses("pred", pred)[0], _as_poses("ref", ref)[0]
    cam = b @ AP_REORIENT  # true camera-to-world, camera axes as columns
    d = invert(a @ AP_REORIENT)[:3, 3] - invert(cam)[:3, 3]  # the CTA centre in each camera's own frame
    w = matrix_to_axis_angle(cam[:3, :3].T @ a[:3, :3] @ AP_REORIENT[:3, :3])  # rotation error, camera axes
    return {
        "in_plane_mm": float(np.hypot(d[0], d[1])),
        "depth_mm": float(abs(d[2])),
        "in_plane_rotation_deg": float(np.degrees(abs(w[2]))),
        "out_of_plane_rotation_deg": float(np.degrees(np.hypot(w[0], w[1]))),
    }


def view_accuracy(pred: ArrayLike, ref: ArrayLike) -> float:
    """Fraction of view labels (0 LAT-, 1 PA, 2 LAT+) predicted correctly."""
    p, r = np.asarray(pred).reshape(-1), np.asarray(ref).reshape(-1)
    if p.shape != r.shape or p.size == 0:
        raise ValueError(f"need the same non-zero number of predicted and reference views, got {p.size} and {r.size}")
    for name, labels in (("pred", p), ("ref", r)):
        if ((labels < 0) | (labels >= len(VIEW_NAMES))).any():
            raise ValueError(f"{name} view labels must be in 0..{len(VIEW_NAMES) - 1} ({', '.join(VIEW_NAMES)})")
    return float((p == r).mean())
