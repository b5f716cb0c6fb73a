"""Training pose sampling about the isoposes and Refine perturbations.

Poses are camera-to-world ``(B, 4, 4)`` in the centred CTA frame (mm, rad);
Init raw targets follow :func:`geopose.nets.decoding.decode_init_pose`, Refine raw
targets :func:`geopose.nets.decoding.residual_from_raw` (docs/conventions.md 1, 4, 6);
:func:`init_pose_tensor` and :func:`residual_tensor` are the same decodings in torch,
differentiable, for the training losses.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .. import contract as C
from ..geometry.rigid import RigidTransform, matrix_to_axis_angle, pose_from_params
from . import recipe as R


def init_pose_tensor(raw: Tensor, view: Tensor) -> Tensor:
    """Init raw ``(B, 6)`` + view labels ``(B,)`` -> pose ``(B, 4, 4)`` (differentiable
    :func:`geopose.nets.decoding.decode_init_pose`)."""
    anchors = torch.tensor(C.VIEW_ANCHOR_RAD, dtype=raw.dtype, device=raw.device)[view]
    r = raw[:, 0:3] + torch.stack((anchors, torch.zeros_like(anchors), torch.zeros_like(anchors)), dim=1)
    iso = torch.tensor(C.ISO_TRANSLATION_MM, dtype=raw.dtype, device=raw.device)
    return pose_from_params(r, raw[:, 3:6] * C.INIT_TRANSLATION_SCALE_MM + iso, rotation="euler_zyx")


def residual_tensor(raw: Tensor) -> Tensor:
    """Refine raw ``(B, 6)`` -> residual ``D`` ``(B, 4, 4)`` (differentiable
    :func:`geopose.nets.decoding.residual_from_raw`)."""
    w = raw[:, 0:3] * torch.tensor(C.REFINE_ROTATION_SCALE_RAD, dtype=raw.dtype, device=raw.device)
    dt = raw[:, 3:6] * torch.tensor(C.REFINE_TRANSLATION_SCALE_MM, dtype=raw.dtype, device=raw.device)
    return RigidTransform.from_axis_angle(w, dt).matrix


def sample_views(n: int, gen: torch.Generator, device: torch.device | str = "cpu") -> Tensor:
    """``(n,)`` view labels: PA with ``PA_PROBABILITY``, otherwise LAT-/LAT+ 50/50."""
    u = torch.rand(n, generator=gen, device=device)
    side = torch.rand(n, generator=gen, device=device) < 0.5
    lateral = torch.where(side, torch.full_like(side, C.VIEW_LAT_PLUS, dtype=torch.long), C.VIEW_LAT_MINUS)
    return torch.where(u < R.PA_PROBABILITY, torch.full_like(lateral, C.VIEW_PA), lateral)


def sample_init_poses(
    views: Tensor,
    gen: torch.Generator,
    rotation_sd_rad: tuple[float, float, float] = R.INIT_ROTATION_SD_RAD,
    translation_sd_mm: tuple[float, float, float] = R.INIT_TRANSLATION_SD_MM,
) -> tuple[Tensor, Tensor]:
    """Isopose of each view plus Gaussian noise -> (poses ``(B, 4, 4)``, Init raw targets ``(B, 6)``)."""
    dev = views.device
    n = views.shape[0]
    dr = torch.randn(n, 3, generator=gen, device=dev) * torch.tensor(rotation_sd_rad, device=dev)
    dt = torch.randn(n, 3, generator=gen, device=dev) * torch.tensor(translation_sd_mm, device=dev)
    anchors = torch.tensor(C.VIEW_ANCHOR_RAD, device=dev)[views]
    r = dr.clone()
    r[:, 0] += anchors
    t = dt + torch.tensor(C.ISO_TRANSLATION_MM, device=dev)
    raw = torch.cat((dr, dt / C.INIT_TRANSLATION_SCALE_MM), dim=1)
    return pose_from_params(r, t, rotation="euler_zyx"), raw


@dataclass(frozen=True)
class PerturbationScale:
    """Refine perturbation sd per view family (axis-angle rad, translation mm)."""

    lat_rotation_rad: tuple[float, float, float] = R.REFINE_LAT_ROTATION_SD_RAD
    lat_translation_mm: tuple[float, float, float] = R.REFINE_LAT_TRANSLATION_SD_MM
    pa_rotation_rad: tuple[float, float, float] = R.REFINE_PA_ROTATION_SD_RAD
    pa_translation_mm: tuple[float, float, float] = R.REFINE_PA_TRANSLATION_SD_MM

    def to_dict(self) -> dict:
        return {k: list(v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, data: dict) -> "PerturbationScale":
        return cls(**{k: tuple(float(x) for x in v) for k, v in data.items()})


def sample_refine_perturbations(
    views: Tensor, gen: torch.Generator, scale: PerturbationScale = PerturbationScale()
) -> tuple[Tensor, Tensor]:
    """Residuals ``D (B, 4, 4)`` (build ``T_noisy = D @ T_opt``) and their Refine raw targets ``(B, 6)``."""
    dev = views.device
    n = views.shape[0]
    pa = (views == C.VIEW_PA)[:, None]
    rot_sd = torch.where(pa, torch.tensor(scale.pa_rotation_rad, device=dev), torch.tensor(scale.lat_rotation_rad, device=dev))
    tr_sd = torch.where(
        pa, torch.tensor(scale.pa_translation_mm, device=dev), torch.tensor(scale.lat_translation_mm, device=dev)
    )
    w = torch.randn(n, 3, generator=gen, device=dev) * rot_sd
    dt = torch.randn(n, 3, generator=gen, device=dev) * tr_sd
    raw = torch.cat(
        (w / torch.tensor(C.REFINE_ROTATION_SCALE_RAD, device=dev), dt / torch.tensor(C.REFINE_TRANSLATION_SCALE_MM, device=dev)),
        dim=1,
    )
    return RigidTransform.from_axis_angle(w, dt).matrix, raw


def residual_params(pred: Tensor, ref: Tensor) -> tuple[Tensor, Tensor]:
    """``D`` with ``pred = D @ ref`` as (axis-angle ``w`` rad ``(B, 3)``, ``dt`` mm ``(B, 3)``), D = [[R(w), R(w) dt]]."""
    D = pred.double() @ torch.linalg.inv(ref.double())
    w = matrix_to_axis_angle(D[:, :3, :3])
    dt = (D[:, :3, :3].transpose(-1, -2) @ D[:, :3, 3:4])[..., 0]
    return w, dt


def calibrated_scale(pred: Tensor, ref: Tensor, views: Tensor) -> PerturbationScale:
    """Perturbation sd per view family from measured Init residuals (``pred = D @ ref``).

    The RMS of each residual component, clamped to ``CALIBRATION_CLAMP`` x the recipe's sd
    (a family without samples keeps the recipe's sd).
    """
    w, dt = residual_params(pred, ref)
    default = PerturbationScale()
    lo, hi = R.CALIBRATION_CLAMP

    def rms(x: Tensor, mask: Tensor, fallback: tuple[float, float, float]) -> tuple[float, float, float]:
        if not bool(mask.any()):
            return fallback
        measured = x[mask].pow(2).mean(0).sqrt()
        base = torch.tensor(fallback, dtype=measured.dtype, device=measured.device)
        return tuple(float(v) for v in torch.minimum(torch.maximum(measured, lo * base), hi * base))

    pa = views == C.VIEW_PA
    return PerturbationScale(
        lat_rotation_rad=rms(w, ~pa, default.lat_rotation_rad),
        lat_translation_mm=rms(dt, ~pa, default.lat_translation_mm),
        pa_rotation_rad=rms(w, pa, default.pa_rotation_rad),
        pa_translation_mm=rms(dt, pa, default.pa_translation_mm),
    )
