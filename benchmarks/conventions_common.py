"""Shared pieces of the left/right checks (docs/conventions.md, section 7;
``bench_conventions.py``, ``Testing/Python/test_conventions*.py``): where DICOM says a C-arm
stores a point (coded from the standard's text alone, not from our geometry), face-side
measures for lateral images, and the tilted GE head CT resampled from its slice positions.

Needs numpy and torch (plus our ``geopose`` package from ``Logic/`` of this checkout if it
is not installed); SimpleITK for the GE head.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
try:
    import geopose  # noqa: F401
except ImportError:  # a bare machine: use the checkout's sources
    sys.path.insert(0, str(REPO / "Logic"))

from geopose.geometry import CArmAngles, Detector  # noqa: E402
from geopose.render import DRR  # noqa: E402
from geopose.volume import Volume  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

#: Teeth: the densest tissue of a head CT (enamel, fillings), HU.
TEETH_HU = 2000.0
#: Head (soft tissue and bone), HU.
HEAD_HU = -300.0
#: In-plane block size (pixels) of the GE head resampling: 0.49 mm -> 1.95 mm.
GE_BLOCK_PX = 4
#: Slice step (mm) of the resampled GE head.
GE_SLICE_MM = 2.0


def dicom_axes(primary_deg: float, secondary_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors in the patient's RAS frame (head-first supine) from DICOM alone.

    ``u``: isocentre -> detector. PS3.3 C.8.7.5.1.2: at 0/0 "the patient faces the Image
    Intensifier or digital detector"; the primary angle is a longitude, "+90 degrees at the
    patient left hand side (LAO) and -90 at the patient right hand side (RAO)"; the secondary a
    latitude, "+90 degrees corresponds to the cranial direction". The source is opposite.
    ``x_col``: direction of increasing column; ``z_up``: image up (decreasing row). PS3.3
    C.8.19.6.13.1.2: Xp "from left to right of the detector plane looking towards the source",
    Zp "from bottom to top", Yp from the isocentre to the source; XA images are "patient-oriented
    (i.e. heads-up display)" (PS3.17 FFF.2.1.3.1.2).
    """
    a, b = math.radians(primary_deg), math.radians(secondary_deg)
    u = np.array([-math.sin(a) * math.cos(b), math.cos(a) * math.cos(b), math.sin(b)])
    yp = -u
    superior = np.array([0.0, 0.0, 1.0])
    z_up = superior - superior.dot(yp) * yp
    z_up /= np.linalg.norm(z_up)
    x_col = np.cross(yp, z_up)  # right-handed: Xp x Yp = Zp
    return u, x_col, z_up


def dicom_pixels(points_ras: np.ndarray, angles: CArmAngles, rows: int, cols: int, spacing_mm: float) -> np.ndarray:
    """Where a C-arm with ``angles`` stores world points ``(N, 3)`` (isocentre at the origin):
    (row, col) px, central ray through the detector centre, the real source ``SOD`` behind the
    isocentre (opposite the detector), the image seen from the detector (``dicom_axes``)."""
    u, x_col, z_up = dicom_axes(angles.primary_deg, angles.secondary_deg)
    v = np.asarray(points_ras, float) + angles.sod_mm * u  # from the source
    depth = v @ u
    x = angles.sid_mm * (v @ x_col) / depth
    z = angles.sid_mm * (v @ z_up) / depth
    return np.stack(((rows - 1) / 2 - z / spacing_mm, (cols - 1) / 2 + x / spacing_mm), axis=-1)


def face_side_of_render(cta: Volume, labels: Volume, pose, detector: Detector) -> float:
    """Column of the rendered teeth (label 1) minus column of the rendered head (labels 1, 2), px:
    > 0 puts the face towards the last column. Intensity centroids of our DRR's label channels."""
    drr = DRR.from_volume(cta, detector, labels, {"teeth": [1], "head": [1, 2]})
    with torch.no_grad():
        img = drr(pose, channels=(1, 2))[0].double()
    cols = torch.arange(detector.cols, dtype=torch.float64)
    centroid = (img.sum(1) * cols).sum(-1) / img.sum((1, 2))
    return float(centroid[0] - centroid[1])


def teeth_and_head_labels(cta: Volume) -> Volume:
    """Label map: 1 teeth (> ``TEETH_HU``), 2 the rest of the head (> ``HEAD_HU``), 0 air."""
    return cta.like(np.where(cta.array > TEETH_HU, 1, np.where(cta.array > HEAD_HU, 2, 0)).astype(np.uint8))


def face_side_of_lateral_cranium_mask(mask: np.ndarray) -> float:
    """Sign (+1: face towards the last column) of where the cranium's floor is higher in a
    lateral view: the anterior cranial fossa lies above the orbits, the posterior fossa reaches
    down to the foramen magnum, so the lowest row of the cranium silhouette rises towards the
    face. Slope of a line through the lowest mask row of the inner 80 % of its columns."""
    cols = np.flatnonzero(mask.any(axis=0))
    inner = cols[int(0.1 * len(cols)) : int(0.9 * len(cols)) + 1]
    lowest = np.array([np.flatnonzero(mask[:, c]).max() for c in inner], float)
    slope = np.polyfit(inner.astype(float), lowest, 1)[0]
    return float(-np.sign(slope))


def ge_head_volume(folder: str | Path) -> Volume:
    """The GE head CT (``shared/data/ge_head_ct_tilt``: 18.5 deg gantry tilt, uneven slice
    positions) resampled onto a regular RAS grid from every slice's ImagePositionPatient:
    ``GE_BLOCK_PX`` x ``GE_BLOCK_PX`` block means in plane, linear interpolation between the
    tilted slices at ``GE_SLICE_MM``. For figures only (the library's loader is being fixed
    to do this properly)."""
    import SimpleITK as sitk

    slices = []
    for f in sorted(Path(folder).glob("*.dcm")):
        img = sitk.ReadImage(str(f))
        slices.append((np.array(img.GetOrigin()), sitk.GetArrayFromImage(img)[0].astype(np.float32)))
    if not slices:
        raise FileNotFoundError(f"no DICOM slices in {folder}")
    direction = np.array(sitk.ReadImage(str(next(Path(folder).glob("*.dcm")))).GetDirection()).reshape(3, 3)
    row_dir, col_dir = direction[:, 0], direction[:, 1]  # LPS: along a row (columns), along a column (rows)
    if not (np.allclose(row_dir, [1, 0, 0], atol=1e-6) and abs(col_dir[0]) < 1e-6):
        raise ValueError("expected axial slices tilted about the patient's left-right axis")
    slices.sort(key=lambda s: s[0][2])
    origins = np.array([s[0] for s in slices])
    if not np.allclose(origins[:, :2], origins[0, :2], atol=1e-3):
        raise ValueError("expected slices that differ only in their table position (z)")
    spacing = float(img.GetSpacing()[0])
    b = GE_BLOCK_PX
    stack = np.stack([s[1] for s in slices])
    n, h, w = stack.shape
    stack = stack[:, : h // b * b, : w // b * b].reshape(n, h // b, b, w // b, b).mean((2, 4))
    h, w = stack.shape[1:]
    # Pixel (r, c) of a slice at origin o: LPS = o + (c * dx) * row_dir + (r * dy) * col_dir (block centres).
    step = spacing * b
    r = np.arange(h) * step + (b - 1) / 2 * spacing
    z_lo, z_hi = origins[:, 2].min() + r.max() * col_dir[2], origins[:, 2].max() + r.min() * col_dir[2]
    z = np.arange(min(z_lo, z_hi), max(z_lo, z_hi), GE_SLICE_MM)
    out = np.full((len(z), h, w), -1024.0, np.float32)
    for row in range(h):
        zeta = z - r[row] * col_dir[2]  # the slice origin whose plane passes through (row, z)
        idx = np.interp(zeta, origins[:, 2], np.arange(n), left=np.nan, right=np.nan)
        ok = np.isfinite(idx)
        lo = np.floor(idx[ok]).astype(int)
        hi = np.minimum(lo + 1, n - 1)
        f = (idx[ok] - lo)[:, None]
        out[ok, row, :] = (1 - f) * stack[lo, row, :] + f * stack[hi, row, :]
    lps = np.eye(4)
    lps[:3, 0] = row_dir * step
    lps[:3, 1] = np.array([0.0, col_dir[1], 0.0]) * step
    lps[:3, 2] = (0.0, 0.0, GE_SLICE_MM)
    lps[:3, 3] = origins[0] + (b - 1) / 2 * spacing * (row_dir + np.array([0.0, col_dir[1], 0.0]))
    lps[2, 3] = z[0]
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps
    return Volume(out, ras, {"name": "ge_head_ct_tilt (resampled for figures)"})
