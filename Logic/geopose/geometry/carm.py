"""C-arm projection geometry: detector intrinsics, the AP reorientation,
isoposes, view labels, DICOM positioner angles, projection and back-projection.

Frames (see ``shared/CONVENTIONS.md`` sections 1-2):

* *camera*: source at the origin, detector plane at ``z = SDD`` (mm). Pixel
  ``(row i, col j)`` lies at ``x = ((W-1)/2 - j) * delx + x0``,
  ``y = ((H-1)/2 - i) * dely + y0`` (the column axis is reversed).
* *world*: the centred CTA frame (RAS axes, origin at the voxel-grid centre).
  A pose ``T`` is camera-to-world, applied after the AP reorientation:
  ``world = T @ AP_REORIENT @ camera``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from .. import contract as C
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

#: Camera (x, y, z) -> (x, -z, y): the camera's principal axis becomes world -y.
AP_REORIENT = torch.tensor(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
    dtype=torch.float64,
)


@dataclass(frozen=True)
class Detector:
    """Flat-panel intrinsics. ``spacing_mm = (row spacing dely, column spacing delx)``;
    ``principal_offset_mm = (x0, y0)`` shifts the image centre in the camera frame."""

    rows: int
    cols: int
    spacing_mm: tuple[float, float]
    sdd_mm: float
    principal_offset_mm: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if self.rows < 1 or self.cols < 1:
            raise ValueError(f"detector needs at least 1x1 pixels, got {self.rows}x{self.cols}")
        if min(self.spacing_mm) <= 0 or not all(math.isfinite(s) for s in self.spacing_mm):
            raise ValueError(f"detector pixel spacing must be positive mm, got {self.spacing_mm}")
        if not (self.sdd_mm > 0 and math.isfinite(self.sdd_mm)):
            raise ValueError(f"source-to-detector distance must be positive mm, got {self.sdd_mm}")

    @classmethod
    def model(cls) -> "Detector":
        """The fixed network geometry K0: 256 x 256, 1.2 mm, SDD 1020 mm."""
        s = C.MODEL_PIXEL_SPACING_MM
        return cls(C.MODEL_DETECTOR_PX, C.MODEL_DETECTOR_PX, (s, s), C.MODEL_SDD_MM)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def size_mm(self) -> tuple[float, float]:
        return (self.rows * self.spacing_mm[0], self.cols * self.spacing_mm[1])

    def resized(self, rows: int, cols: int | None = None) -> "Detector":
        """Same physical field of view sampled on ``rows x cols`` pixels."""
        cols = rows if cols is None else cols
        dy = self.spacing_mm[0] * self.rows / rows
        dx = self.spacing_mm[1] * self.cols / cols
        return replace(self, rows=rows, cols=cols, spacing_mm=(dy, dx))

    def with_sdd(self, sdd_mm: float) -> "Detector":
        return replace(self, sdd_mm=float(sdd_mm))

    def intrinsic_matrix(self) -> Tensor:
        """3x3 pinhole matrix mapping camera (x, y, z) to homogeneous (col, row, 1)."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        f = self.sdd_mm
        return torch.tensor(
            [[-f / dx, 0.0, (self.cols - 1) / 2 + x0 / dx], [0.0, -f / dy, (self.rows - 1) / 2 + y0 / dy], [0.0, 0.0, 1.0]],
            dtype=torch.float64,
        )

    def camera_points(self, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
        """``(H, W, 3)`` camera-frame positions (mm) of every pixel centre on the detector plane."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        i = torch.arange(self.rows, dtype=dtype, device=device)
        j = torch.arange(self.cols, dtype=dtype, device=device)
        y = ((self.rows - 1) / 2 - i) * dy + y0
        x = ((self.cols - 1) / 2 - j) * dx + x0
        yy, xx = torch.meshgrid(y, x, indexing="ij")
        return torch.stack((xx, yy, torch.full_like(xx, self.sdd_mm)), dim=-1)

    def camera_to_pixel(self, xyz: Tensor) -> Tensor:
        """Camera-frame points ``(..., 3)`` -> pixel ``(..., 2)`` as (row, col), float."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        u = self.sdd_mm * xyz[..., 0] / xyz[..., 2]
        v = self.sdd_mm * xyz[..., 1] / xyz[..., 2]
        row = (self.rows - 1) / 2 - (v - y0) / dy
        col = (self.cols - 1) / 2 - (u - x0) / dx
        return torch.stack((row, col), dim=-1)

    def pixel_to_camera(self, rc: Tensor) -> Tensor:
        """Pixel ``(..., 2)`` (row, col) -> camera-frame point on the detector plane (mm)."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        y = ((self.rows - 1) / 2 - rc[..., 0]) * dy + y0
        x = ((self.cols - 1) / 2 - rc[..., 1]) * dx + x0
        return torch.stack((x, y, torch.full_like(x, self.sdd_mm)), dim=-1)


def _reorient(dtype: torch.dtype, device) -> Tensor:
    return AP_REORIENT.to(dtype=dtype, device=device)


def isopose(view: int | Tensor, dtype: torch.dtype = torch.float32, device=None) -> RigidTransform:
    """Isocentric pose of a view label (0 LAT-, 1 PA, 2 LAT+); batched over a tensor of labels."""
    views = torch.as_tensor(view, device=device).reshape(-1).long()
    anchors = torch.tensor(C.VIEW_ANCHOR_RAD, dtype=dtype, device=device)[views]
    r = torch.zeros(len(views), 3, dtype=dtype, device=device)
    r[:, 0] = anchors
    t = torch.tensor(C.ISO_TRANSLATION_MM, dtype=dtype, device=device).expand(len(views), 3)
    return RigidTransform.from_euler_zyx(r, t)


def view_from_primary_angle(primary_deg: float) -> int:
    """View label from DICOM PositionerPrimaryAngle ``alpha`` (deg): with ``s = -alpha``,
    ``s > 45`` is LAT+ (2), ``s < -45`` is LAT- (0), otherwise PA (1)."""
    s = -float(primary_deg)
    if s > C.LATERAL_THRESHOLD_DEG:
        return C.VIEW_LAT_PLUS
    if s < -C.LATERAL_THRESHOLD_DEG:
        return C.VIEW_LAT_MINUS
    return C.VIEW_PA


def is_lateral_primary_angle(primary_deg: float) -> bool:
    return view_from_primary_angle(primary_deg) != C.VIEW_PA


@dataclass(frozen=True)
class CArmAngles:
    """C-arm acquisition geometry in DICOM terms.

    ``primary_deg``: PositionerPrimaryAngle (LAO positive), ``secondary_deg``:
    PositionerSecondaryAngle (cranial positive), ``sid_mm``: DistanceSourceToDetector,
    ``sod_mm``: DistanceSourceToPatient (source to isocentre). ``roll_deg`` is an
    in-plane detector rotation and ``offset_mm`` (x, z) an off-isocentre shift in
    the rotated camera frame; both are 0 for an isocentric acquisition.
    """

    primary_deg: float
    secondary_deg: float
    sid_mm: float
    sod_mm: float
    roll_deg: float = 0.0
    offset_mm: tuple[float, float] = (0.0, 0.0)


def pose_from_carm_angles(angles: CArmAngles, dtype: torch.dtype = torch.float64) -> RigidTransform:
    """DICOM positioner angles -> camera-to-world pose about the world origin (isocentre).

    Mapping (GeoPose convention, consistent with the view rule):
    ``r = (-primary, roll, -secondary)`` rad (Euler ZYX), ``t = (offset_x, SOD, offset_z)`` mm.
    Primary 0 is the PA isopose, -90 is LAT+ and +90 is LAT-; the detector is
    ``SID - SOD`` beyond the isocentre. The SID is a detector property (``Detector.sdd_mm``).
    """
    r = torch.tensor(
        [[-math.radians(angles.primary_deg), math.radians(angles.roll_deg), -math.radians(angles.secondary_deg)]],
        dtype=dtype,
    )
    t = torch.tensor([[angles.offset_mm[0], angles.sod_mm, angles.offset_mm[1]]], dtype=dtype)
    return RigidTransform.from_euler_zyx(r, t)


def carm_angles_from_pose(pose: RigidTransform | Tensor, sid_mm: float) -> list[CArmAngles]:
    """Inverse of :func:`pose_from_carm_angles` for each pose in the batch."""
    r, t = params_from_pose(as_transform(pose).matrix.double())
    out = []
    for ri, ti in zip(r.tolist(), t.tolist()):
        out.append(
            CArmAngles(
                primary_deg=-math.degrees(ri[0]),
                secondary_deg=-math.degrees(ri[2]),
                sid_mm=float(sid_mm),
                sod_mm=ti[1],
                roll_deg=math.degrees(ri[1]),
                offset_mm=(ti[0], ti[2]),
            )
        )
    return out


def _camera_to_world(pose: RigidTransform | Tensor) -> Tensor:
    m = as_transform(pose).matrix
    return m @ _reorient(m.dtype, m.device)


def source_and_detector_points(pose: RigidTransform | Tensor, detector: Detector) -> tuple[Tensor, Tensor]:
    """World positions (mm) of the sources ``(B, 3)`` and of every pixel ``(B, H, W, 3)``."""
    M = _camera_to_world(pose)
    pts = detector.camera_points(dtype=M.dtype, device=M.device)
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
