"""C-arm pose algebra in torch (batched, differentiable): isoposes, DICOM positioner
angles <-> poses, projection and back-projection.

The detector, the DICOM angles, the view rule and ``AP_REORIENT`` live in
``detector.py`` (numpy only) and are re-exported here. Frames: ``shared/CONVENTIONS.md``
sections 1-2; a pose ``T`` is camera-to-world, ``world = T @ AP_REORIENT @ camera``,
with world the centred CTA frame (RAS axes, origin at the voxel-grid centre, mm).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .. import contract as C
from .detector import (
    AP_REORIENT, CArmAngles, Detector, carm_angles_from_params, carm_pose_params, is_lateral_primary_angle, view_from_primary_angle,
)
from .rigid import RigidTransform, as_transform, params_from_pose

__all__ = [
    "AP_REORIENT",
    "Detector",
    "isopose",
    "view_from_primary_angle",
    "is_lateral_primary_angle",
    "pose_from_carm_angles",
    "carm_angles_from_pose",
    "CArmAngles",
    "source_and_detector_points",
    "project_points",
    "backproject_pixels",
]


def _reorient(dtype: torch.dtype, device) -> Tensor:
    return torch.tensor(AP_REORIENT, dtype=dtype, device=device)


def isopose(view: int | Tensor, dtype: torch.dtype = torch.float32, device=None) -> RigidTransform:
    """Isocentric pose of a view label (0 LAT-, 1 PA, 2 LAT+); batched over a tensor of labels."""
    views = torch.as_tensor(view, device=device).reshape(-1).long()
    anchors = torch.tensor(C.VIEW_ANCHOR_RAD, dtype=dtype, device=device)[views]
    r = torch.zeros(len(views), 3, dtype=dtype, device=device)
    r[:, 0] = anchors
    t = torch.tensor(C.ISO_TRANSLATION_MM, dtype=dtype, device=device).expand(len(views), 3)
    return RigidTransform.from_euler_zyx(r, t)


def pose_from_carm_angles(angles: CArmAngles, dtype: torch.dtype = torch.float64) -> RigidTransform:
    """DICOM positioner angles -> camera-to-world pose ``(1, 4, 4)`` about the isocentre
    (mapping: :func:`geopose.geometry.detector.carm_pose_params`)."""
    r, t = carm_pose_params(angles)
    return RigidTransform.from_euler_zyx(torch.as_tensor(r, dtype=dtype)[None], torch.as_tensor(t, dtype=dtype)[None])


def carm_angles_from_pose(pose: RigidTransform | Tensor, sid_mm: float) -> list[CArmAngles]:
    """Inverse of :func:`pose_from_carm_angles` for each pose in the batch."""
    r, t = params_from_pose(as_transform(pose).matrix.double())
    return [carm_angles_from_params(ri, ti, sid_mm) for ri, ti in zip(r.cpu().numpy(), t.cpu().numpy())]


def _camera_to_world(pose: RigidTransform | Tensor) -> Tensor:
    m = as_transform(pose).matrix
    return m @ _reorient(m.dtype, m.device)


def source_and_detector_points(pose: RigidTransform | Tensor, detector: Detector) -> tuple[Tensor, Tensor]:
    """World positions (mm) of the sources ``(B, 3)`` and of every pixel ``(B, H, W, 3)``."""
    M = _camera_to_world(pose)
    pts = torch.as_tensor(detector.camera_points(), dtype=M.dtype, device=M.device)
    world = torch.einsum("bij,hwj->bhwi", M[:, :3, :3], pts) + M[:, None, None, :3, 3]
    return M[:, :3, 3], world


def project_points(pose: RigidTransform | Tensor, detector: Detector, points_mm: Tensor) -> tuple[Tensor, Tensor]:
    """World points ``(B, N, 3)`` or ``(N, 3)`` -> pixels ``(B, N, 2)`` (row, col) and depth (mm along the axis)."""
    M = _camera_to_world(pose)
    cam = RigidTransform(M).inverse().apply(points_mm.to(M.dtype))
    return detector.camera_to_pixel(cam), cam[..., 2]


def backproject_pixels(pose: RigidTransform | Tensor, detector: Detector, pixels: Tensor) -> tuple[Tensor, Tensor]:
    """Pixels ``(B, N, 2)`` (row, col) -> ray origins ``(B, 1, 3)`` (the source) and unit directions ``(B, N, 3)``."""
    M = _camera_to_world(pose)
    cam = detector.pixel_to_camera(pixels.to(M.dtype))
    world = RigidTransform(M).apply(cam)
    src = M[:, None, :3, 3]
    d = world - src
    return src, d / d.norm(dim=-1, keepdim=True)
