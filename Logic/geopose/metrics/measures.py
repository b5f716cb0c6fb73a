"""Image similarity, losses and registration/pose metrics.

Images are ``(B, C, H, W)`` torch tensors; similarities are computed per batch
item (and averaged over channels) and are differentiable. Distances are in
pixels (px) on the detector, millimetres at the detector (mm) or at the
isocentre (detector mm x SOD/SDD). Poses are camera-to-world ``(B, 4, 4)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
import SimpleITK as sitk
import torch
import torch.nn.functional as F
from torch import Tensor

from ..contract import MNCC_GLOBAL_WEIGHT, MNCC_PATCH_PX, MODEL_SDD_MM, NCC_EPS, VIEW_NAMES
from ..geometry.rigid import RigidTransform, params_from_pose, rotation_angle_rad

__all__ = [
    "ncc",
    "local_ncc",
    "mncc",
    "generalized_dice_loss",
    "MPCD",
    "mpcd",
    "mask_points",
    "skeletonize",
    "cldice",
    "PoseErrors",
    "pose_errors",
    "double_geodesic_mm",
    "view_accuracy",
]

# Distances are evaluated against the reference in chunks of this many query points.
_CDIST_CHUNK = 4096


def _check_pair(a: Tensor, b: Tensor) -> None:
    if a.ndim != 4 or a.shape != b.shape:
        raise ValueError(f"expected two (B, C, H, W) images of the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")


# ------------------------------------------------------------------ similarity
# NCC scale convention: images are compared on the scale of the networks' min-max
# inputs, i.e. each image channel is first shifted to zero mean and divided by its
# (max - min) range, so ``eps`` acts on a [0, 1]-range image whatever the input
# units (DSA grey values, DRR line integrals). This also keeps the pooled
# E[x^2] - E[x]^2 patch moments accurate in float32.


def _unit_range(x: Tensor) -> Tensor:
    """Zero mean and unit (max - min) range per image channel; a constant channel becomes 0."""
    x = x - x.mean(dim=(-2, -1), keepdim=True)
    span = x.amax(dim=(-2, -1), keepdim=True) - x.amin(dim=(-2, -1), keepdim=True)
    return torch.where(span > 0, x / torch.where(span > 0, span, torch.ones_like(span)), torch.zeros_like(x))


def ncc(a: Tensor, b: Tensor, eps: float = NCC_EPS) -> Tensor:
    """Global normalised cross-correlation ``(B,)`` in [-1, 1].

    Each image channel (unit range, see above) is z-scored, ``(x - mean) / sqrt(var + eps)``;
    the NCC is the mean product, averaged over channels.
    """
    _check_pair(a, b)
    a, b = _unit_range(a).flatten(2), _unit_range(b).flatten(2)
    za = (a - a.mean(-1, keepdim=True)) / torch.sqrt(a.var(-1, unbiased=False, keepdim=True) + eps)
    zb = (b - b.mean(-1, keepdim=True)) / torch.sqrt(b.var(-1, unbiased=False, keepdim=True) + eps)
    return (za * zb).mean(-1).mean(-1)


def local_ncc(a: Tensor, b: Tensor, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> Tensor:
    """Mean NCC ``(B,)`` over all ``patch_px`` x ``patch_px`` patches (stride 1, no padding).

    Each patch is z-scored like :func:`ncc`; local moments come from average pooling,
    and each patch value is clamped to [-1, 1] against float32 rounding.
    """
    _check_pair(a, b)
    if min(a.shape[-2:]) < patch_px:
        raise ValueError(f"images of {tuple(a.shape[-2:])} px are smaller than the {patch_px} px NCC patch")
    a, b = _unit_range(a), _unit_range(b)
    pool = lambda x: F.avg_pool2d(x, patch_px, stride=1)  # noqa: E731
    mu_a, mu_b = pool(a), pool(b)
    var_a = (pool(a * a) - mu_a * mu_a).clamp_min(0)
    var_b = (pool(b * b) - mu_b * mu_b).clamp_min(0)
    cov = pool(a * b) - mu_a * mu_b
    patch_ncc = (cov / torch.sqrt((var_a + eps) * (var_b + eps))).clamp(-1.0, 1.0)
    return patch_ncc.mean(dim=(-2, -1)).mean(-1)


def mncc(a: Tensor, b: Tensor, patch_px: int = MNCC_PATCH_PX, eps: float = NCC_EPS) -> Tensor:
    """Multiscale NCC ``(B,)``: ``MNCC_GLOBAL_WEIGHT`` x global NCC + the rest x mean patch NCC."""
    return MNCC_GLOBAL_WEIGHT * ncc(a, b, eps) + (1.0 - MNCC_GLOBAL_WEIGHT) * local_ncc(a, b, patch_px, eps)


def generalized_dice_loss(pred: Tensor, target: Tensor, *, with_background: bool = True) -> Tensor:
    """Generalised Dice loss (Sudre et al. 2017) ``(B,)`` in [0, 1].

    ``pred`` holds soft foreground probabilities ``(B, C, H, W)`` in [0, 1], ``target``
    the reference masks of the same shape. Classes are the channels, plus their
    complements when ``with_background`` (the two-class form for binary masks).
    Class weights are ``1 / max(sum(target), 1)^2`` (target pixel counts).
    """
    _check_pair(pred, target)
    target = target.to(pred.dtype)
    if with_background:
        pred = torch.cat((pred, 1.0 - pred), dim=1)
        target = torch.cat((target, 1.0 - target), dim=1)
    p, g = pred.flatten(2), target.flatten(2)
    weights = 1.0 / g.sum(-1).clamp_min(1.0) ** 2
    overlap = (weights * (p * g).sum(-1)).sum(-1)
    total = (weights * (p + g).sum(-1)).sum(-1)
    dice = torch.where(total > 0, 2.0 * overlap / torch.where(total > 0, total, torch.ones_like(total)), torch.ones_like(total))
    return 1.0 - dice


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
    ref = torch.from_numpy(reference)
    out = [torch.cdist(torch.from_numpy(query[i : i + _CDIST_CHUNK]), ref).amin(1) for i in range(0, len(query), _CDIST_CHUNK)]
    return torch.cat(out).numpy()


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


def _as_mask(name: str, mask: ArrayLike | Tensor) -> np.ndarray:
    arr = np.asarray(mask.detach().cpu() if isinstance(mask, Tensor) else mask)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D mask, got shape {arr.shape}")
    return arr > 0


def mask_points(mask: ArrayLike | Tensor) -> np.ndarray:
    """(row, col) pixel coordinates ``(N, 2)`` of the non-zero pixels of a 2-D mask."""
    return np.argwhere(_as_mask("mask", mask)).astype(np.float64)


def skeletonize(mask: ArrayLike | Tensor) -> np.ndarray:
    """One-pixel-wide skeleton (bool, same shape) of a 2-D mask by morphological thinning."""
    image = sitk.GetImageFromArray(_as_mask("mask", mask).astype(np.uint8))
    return sitk.GetArrayFromImage(sitk.BinaryThinning(image)).astype(bool)


def cldice(pred_mask: ArrayLike | Tensor, ref_mask: ArrayLike | Tensor) -> float:
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
def _as_poses(name: str, pose: RigidTransform | Tensor) -> Tensor:
    m = pose.matrix if isinstance(pose, RigidTransform) else torch.as_tensor(pose)
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must be (B, 4, 4) poses, got shape {tuple(m.shape)}")
    return m.reshape(-1, 4, 4).to(torch.float64)


def double_geodesic_mm(pred: RigidTransform | Tensor, ref: RigidTransform | Tensor, sdd_mm: float = MODEL_SDD_MM) -> Tensor:
    """``sqrt((SDD/2 * angle)^2 + |c1 - c2|^2)`` (mm) ``(B,)``; ``c`` = source position (world, mm)."""
    a, b = _as_poses("pred", pred), _as_poses("ref", ref)
    angle = rotation_angle_rad(a[:, :3, :3].transpose(-1, -2) @ b[:, :3, :3])
    return torch.sqrt((sdd_mm / 2.0 * angle) ** 2 + ((a[:, :3, 3] - b[:, :3, 3]) ** 2).sum(-1))


@dataclass(frozen=True)
class PoseErrors:
    """Per-item pose errors (pred - ref); tensors ``(B,)`` or ``(B, 3)``, float64."""

    rotation_deg: Tensor  # geodesic angle of R_pred^T R_ref
    euler_deg: Tensor  # Euler ZYX (rz, ry, rx) differences wrapped to (-180, 180]
    translation_mm: Tensor  # rotated-frame t differences (GeoPose parameters)
    translation_norm_mm: Tensor
    source_distance_mm: Tensor  # distance between the X-ray source positions (world)
    double_geodesic_mm: Tensor


def pose_errors(pred: RigidTransform | Tensor, ref: RigidTransform | Tensor, sdd_mm: float = MODEL_SDD_MM) -> PoseErrors:
    """Errors of predicted poses against references (both ``(B, 4, 4)`` or RigidTransform)."""
    a, b = _as_poses("pred", pred), _as_poses("ref", ref)
    if a.shape != b.shape:
        raise ValueError(f"pred has {a.shape[0]} poses and ref {b.shape[0]}")
    (ra, ta), (rb, tb) = params_from_pose(a), params_from_pose(b)
    d_euler = torch.remainder(ra - rb + math.pi, 2 * math.pi) - math.pi
    d_euler = torch.where(d_euler <= -math.pi, d_euler + 2 * math.pi, d_euler)
    dt = ta - tb
    return PoseErrors(
        rotation_deg=torch.rad2deg(rotation_angle_rad(a[:, :3, :3].transpose(-1, -2) @ b[:, :3, :3])),
        euler_deg=torch.rad2deg(d_euler),
        translation_mm=dt,
        translation_norm_mm=dt.norm(dim=-1),
        source_distance_mm=(a[:, :3, 3] - b[:, :3, 3]).norm(dim=-1),
        double_geodesic_mm=double_geodesic_mm(a, b, sdd_mm),
    )


def view_accuracy(pred: ArrayLike | Tensor, ref: ArrayLike | Tensor) -> float:
    """Fraction of view labels (0 LAT-, 1 PA, 2 LAT+) predicted correctly."""
    p, r = torch.as_tensor(pred).reshape(-1), torch.as_tensor(ref).reshape(-1)
    if p.shape != r.shape or p.numel() == 0:
        raise ValueError(f"need the same non-zero number of predicted and reference views, got {p.numel()} and {r.numel()}")
    for name, labels in (("pred", p), ("ref", r)):
        if bool(((labels < 0) | (labels >= len(VIEW_NAMES))).any()):
            raise ValueError(f"{name} view labels must be in 0..{len(VIEW_NAMES) - 1} ({', '.join(VIEW_NAMES)})")
    return float((p == r).double().mean())
