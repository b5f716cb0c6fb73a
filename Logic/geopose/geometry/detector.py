"""The C-arm's acquisition description without any array library beyond numpy:
detector intrinsics, DICOM positioner angles, the view rule and the AP reorientation.

Frames (``docs/conventions.md`` sections 1-2): in the *camera* frame the source
is at the origin and the detector plane at ``z = SDD`` (mm); pixel ``(row i, col j)``
lies at ``x = ((W-1)/2 - j) * delx + x0``, ``y = ((H-1)/2 - i) * dely + y0`` (the
column axis is reversed). A pose ``T`` is camera-to-world, applied after the AP
reorientation: ``world = T @ AP_REORIENT @ camera``.

Everything here imports without PyTorch; the torch pose algebra is in ``carm.py``.
Detector methods take numpy arrays or torch tensors and answer in the same kind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import contract as C

__all__ = [
    "AP_REORIENT",
    "Detector",
    "CArmAngles",
    "view_from_primary_angle",
    "is_lateral_primary_angle",
    "carm_pose_params",
    "carm_angles_from_params",
]

#: Camera (x, y, z) -> (x, -z, y): the camera's principal axis becomes world -y.
AP_REORIENT = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]], dtype=np.float64
)
AP_REORIENT.setflags(write=False)


def _stack_last(parts: list[Any]) -> Any:
    """Stack along a new last axis, numpy or torch alike (the kind of the first part)."""
    if isinstance(parts[0], np.ndarray):
        return np.stack(parts, axis=-1)
    import torch

    return torch.stack(parts, dim=-1)


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

    def intrinsic_matrix(self) -> np.ndarray:
        """3x3 pinhole matrix mapping camera (x, y, z) to homogeneous (col, row, 1)."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        f = self.sdd_mm
        return np.array(
            [[-f / dx, 0.0, (self.cols - 1) / 2 + x0 / dx], [0.0, -f / dy, (self.rows - 1) / 2 + y0 / dy], [0.0, 0.0, 1.0]]
        )

    def camera_points(self) -> np.ndarray:
        """``(H, W, 3)`` camera-frame positions (mm, float64) of every pixel centre on the detector plane."""
        rows, cols = np.meshgrid(np.arange(self.rows, dtype=np.float64), np.arange(self.cols, dtype=np.float64), indexing="ij")
        return self.pixel_to_camera(np.stack((rows, cols), axis=-1))

    def camera_to_pixel(self, xyz: Any) -> Any:
        """Camera-frame points ``(..., 3)`` -> pixel ``(..., 2)`` as (row, col), float."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        u = self.sdd_mm * xyz[..., 0] / xyz[..., 2]
        v = self.sdd_mm * xyz[..., 1] / xyz[..., 2]
        return _stack_last([(self.rows - 1) / 2 - (v - y0) / dy, (self.cols - 1) / 2 - (u - x0) / dx])

    def pixel_to_camera(self, rc: Any) -> Any:
        """Pixel ``(..., 2)`` (row, col) -> camera-frame point on the detector plane (mm)."""
        dy, dx = self.spacing_mm
        x0, y0 = self.principal_offset_mm
        y = ((self.rows - 1) / 2 - rc[..., 0]) * dy + y0
        x = ((self.cols - 1) / 2 - rc[..., 1]) * dx + x0
        return _stack_last([x, y, x * 0 + self.sdd_mm])


def view_from_primary_angle(primary_deg: float) -> int:
    """View label from DICOM PositionerPrimaryAngle ``alpha`` (deg): ``alpha > 45`` (LAO, detector
    at the patient's left) is LAT+ (2), ``alpha < -45`` (RAO) is LAT- (0), otherwise PA (1): the
    isopose nearest the pose of :func:`carm_pose_params`. The published rule negates ``alpha``,
    which labels every lateral with the side its pixels are the mirror of (docs/conventions.md, 7)."""
    s = float(primary_deg)
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


def carm_pose_params(angles: CArmAngles) -> tuple[np.ndarray, np.ndarray]:
    """DICOM positioner angles -> GeoPose pose parameters about the isocentre (world origin).

    ``r = (primary, roll, secondary)`` rad (Euler ZYX), ``t = (offset_x, SOD, offset_z)`` mm
    (rotated frame): the model source lies ``SOD`` from the isocentre in the direction the
    angles give the detector (PS3.3 C.8.7.5.1.2), so the render shows the patient as the
    stored XA pixels do, seen from the detector (docs/conventions.md, section 7). Primary 0
    is the PA isopose, +90 (LAO) LAT+, -90 (RAO) LAT-; positive secondary (cranial) moves
    the model source towards the head. The model detector is ``SID - SOD`` beyond the
    isocentre (the SID is ``Detector.sdd_mm``).
    """
    r = np.radians([angles.primary_deg, angles.roll_deg, angles.secondary_deg])
    t = np.array([angles.offset_mm[0], angles.sod_mm, angles.offset_mm[1]], dtype=np.float64)
    return r, t


def carm_angles_from_params(r: np.ndarray, t: np.ndarray, sid_mm: float) -> CArmAngles:
    """Inverse of :func:`carm_pose_params` for one pose's ``(r, t)`` (rad, mm)."""
    r, t = np.asarray(r, dtype=np.float64), np.asarray(t, dtype=np.float64)
    return CArmAngles(
        primary_deg=math.degrees(r[0]),
        secondary_deg=math.degrees(r[2]),
        sid_mm=float(sid_mm),
        sod_mm=float(t[1]),
        roll_deg=math.degrees(r[1]),
        offset_mm=(float(t[0]), float(t[2])),
    )
