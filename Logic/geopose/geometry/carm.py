"""Rays and projections for batched torch poses (differentiable): what the torch DRR kernel
and the training losses need.

Frames as in ``poses.py`` (docs/conventions.md sections 1-2): a pose ``T`` is
camera-to-world, ``world = T @ AP_REORIENT @ camera``, world the centred CTA frame (mm).
The numpy functions of the same purpose (inference, evaluation) are in ``poses.py``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .detector import AP_REORIENT, Detector
from .rigid import RigidTransform, as_transform

__all__ = ["ray_points_tensor", "project_points_tensor"]


def _camera_to_world(pose: RigidTransform | Tensor) -> Tensor:
    m = as_transform(pose).matrix
    return m @ torch.tensor(AP_REORIENT, dtype=m.dtype, device=m.device)


def ray_points_tensor(pose: RigidTransform | Tensor, detector: Detector) -> tuple[Tensor, Tensor]:
    """World positions (mm) of the sources ``(B, 3)`` and of every pixel ``(B, H, W, 3)``."""
    M = _camera_to_world(pose)
    pts = torch.as_tensor(detector.camera_points(), dtype=M.dtype, device=M.device)
    world = torch.einsum("bij,hwj->bhwi", M[:, :3, :3], pts) + M[:, None, None, :3, 3]
    return M[:, :3, 3], world


def project_points_tensor(pose: RigidTransform | Tensor, detector: Detector, points_mm: Tensor) -> tuple[Tensor, Tensor]:
    """World points ``(B, N, 3)`` or ``(N, 3)`` -> pixels ``(B, N, 2)`` (row, col) and depth (mm along the axis)."""
    M = _camera_to_world(pose)
    cam = RigidTransform(M).inverse().apply(points_mm.to(M.dtype))
    return detector.camera_to_pixel(cam), cam[..., 2]
