"""The head's midsagittal plane, found by the CT's own mirror symmetry, and a volume reflected across it (SimpleITK).

A head is nearly mirror-symmetric about its midsagittal plane, and that plane is rarely the scanner's: the head
lies turned and tilted in the CT. Reflected across the right plane, the CT's HU (skull, face, soft tissue)
correlate best with themselves. The plane is searched among those whose normal lies within
:data:`MAX_TILT_DEG` of the patient's left-right axis (the header's), turned towards anterior (yaw) and superior
(roll), through the body's centre shifted along the normal, coarse to fine (the last steps on a
:data:`SYMMETRY_GRID_MM` grid).
Frames: LPS physical mm, as SimpleITK reads the volume (``io.sitk_from_volume``).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np
import SimpleITK as sitk

from ..volume import Volume
from .io import sitk_from_volume

__all__ = ["SYMMETRY_GRID_MM", "MAX_TILT_DEG", "Midplane", "midsagittal_plane", "mirrored_across"]

#: Voxel size (mm) of the grid the symmetry is scored on.
SYMMETRY_GRID_MM = 4.0
#: Largest yaw and roll (deg) of the plane searched, from the plane normal to the header's left-right axis.
MAX_TILT_DEG = 15.0
#: HU window the symmetry is scored in (air to dense bone), and the HU above which a voxel is the body.
SYMMETRY_WINDOW_HU = (-200.0, 1600.0)
BODY_HU = -100.0
#: Coarse search step (deg) on the coarse grid, then the refinements' steps (deg for the angles, mm for the shift along
#: the normal) on the fine grid, each trying one step either way on all three (27 planes): 49 + 81 resamples. On 22
#: validation and real-head CTAs it found planes within 0.5 deg of the earlier search's (2.5-deg coarse steps, two
#: 5 x 5 x 3 refinements: 319 resamples) in half the time (experiments/mirror/plane_search.md).
COARSE_STEP_DEG = 5.0
REFINE_STEPS = (2.5, 1.0, 0.5)


@dataclass(frozen=True)
class Midplane:
    """The plane through ``point_lps_mm`` with unit ``normal_lps``; ``yaw_deg`` / ``roll_deg``: its normal turned
    from LPS x towards y (posterior) and z (superior); ``symmetry_ncc``: the NCC of the body's HU with their
    reflection across it."""

    normal_lps: np.ndarray
    point_lps_mm: np.ndarray
    yaw_deg: float
    roll_deg: float
    symmetry_ncc: float

    def reflection(self) -> sitk.AffineTransform:
        """The reflection across the plane, LPS mm -> LPS mm (its own inverse)."""
        n = self.normal_lps
        transform = sitk.AffineTransform(3)
        transform.SetMatrix((np.eye(3) - 2.0 * np.outer(n, n)).ravel().tolist())
        transform.SetTranslation((2.0 * float(self.point_lps_mm @ n) * n).tolist())
        return transform

    def as_dict(self) -> dict:
        return {"normal_lps": self.normal_lps.tolist(), "point_lps_mm": self.point_lps_mm.tolist(),
                "yaw_deg": self.yaw_deg, "roll_deg": self.roll_deg, "symmetry_ncc": self.symmetry_ncc}


def _normal(yaw_deg: float, roll_deg: float) -> np.ndarray:
    n = np.array([1.0, np.tan(np.radians(yaw_deg)), np.tan(np.radians(roll_deg))])
    return n / np.linalg.norm(n)


def midsagittal_plane(cta: Volume) -> Midplane:
    """The plane of best mirror symmetry of ``cta`` (HU) near the one normal to its header's left-right axis: the
    coarse search on a grid twice :data:`SYMMETRY_GRID_MM`, the refinements on that grid."""
    full = sitk.Clamp(sitk.Cast(sitk_from_volume(cta), sitk.sitkFloat32), sitk.sitkFloat32, *SYMMETRY_WINDOW_HU)
    factors = [max(1, int(round(SYMMETRY_GRID_MM / s))) for s in full.GetSpacing()]
    fine, coarse = sitk.BinShrink(full, factors), sitk.BinShrink(full, [2 * f for f in factors])
    values = sitk.GetArrayViewFromImage(fine)
    body = values > BODY_HU
    if not body.any():
        return Midplane(np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.0, 0.0, 0.0)
    kji = np.argwhere(body).mean(axis=0)
    centre = np.array(fine.TransformContinuousIndexToPhysicalPoint(kji[::-1].tolist()))
    coarse_score, fine_score = _symmetry_score(coarse, centre), _symmetry_score(fine, centre)
    angles = np.arange(-MAX_TILT_DEG, MAX_TILT_DEG + 1e-9, COARSE_STEP_DEG)
    best = max((coarse_score(yaw, roll, 0.0), yaw, roll, 0.0) for yaw, roll in product(angles, angles))
    for step in REFINE_STEPS:
        _, yaw0, roll0, shift0 = best
        near = product((-1, 0, 1), repeat=3)
        best = max((fine_score(yaw0 + a * step, roll0 + b * step, shift0 + c * step), yaw0 + a * step, roll0 + b * step,
                    shift0 + c * step) for a, b, c in near)
    ncc, yaw, roll, shift = best
    return Midplane(_normal(yaw, roll), centre + shift * _normal(yaw, roll), float(yaw), float(roll), ncc)


def _symmetry_score(grid: sitk.Image, centre: np.ndarray):
    """``score(yaw_deg, roll_deg, shift_mm)``: the NCC, over the body's voxels of ``grid`` (clamped HU), of the HU
    with their reflection across the plane of that normal through ``centre`` (LPS mm) moved along it."""
    values = sitk.GetArrayViewFromImage(grid)
    body = values > BODY_HU
    x = values[body] - values[body].mean()

    def score(yaw: float, roll: float, shift: float) -> float:
        plane = Midplane(_normal(yaw, roll), centre + shift * _normal(yaw, roll), yaw, roll, 0.0)
        mirrored = sitk.Resample(grid, grid, plane.reflection(), sitk.sitkLinear, SYMMETRY_WINDOW_HU[0])
        y = sitk.GetArrayViewFromImage(mirrored)[body]
        y = y - y.mean()
        return float(x @ y / np.sqrt((x @ x) * (y @ y) + 1e-12))

    return score


def mirrored_across(volume: Volume, plane: Midplane, *, labels: bool = False) -> Volume:
    """``volume`` reflected across ``plane`` on its own grid (header kept): linear for HU, whose voxels from outside
    the grid are air (its minimum); nearest for ``labels``, 0 outside."""
    image = sitk_from_volume(volume)
    fill = 0.0 if labels else float(np.min(volume.array))
    mirrored = sitk.Resample(image, image, plane.reflection(), sitk.sitkNearestNeighbor if labels else sitk.sitkLinear,
                             fill)
    return volume.like(sitk.GetArrayFromImage(mirrored).astype(volume.array.dtype, copy=False))
