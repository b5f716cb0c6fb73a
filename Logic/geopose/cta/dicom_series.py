"""A CT series from a folder of DICOM slices, placed by its slices' own geometry.

Slices are ordered by their position along the slice normal ``n = row x column``
(ImageOrientationPatient) and checked: one orientation, one pixel spacing and one
matrix for all slices; no two slices at one position; the gaps between positions even
within :data:`~geopose.limits.SLICE_GAP_TOLERANCE` (of their median) or
:data:`~geopose.limits.SLICE_GAP_TOLERANCE_MM`, whichever is larger, and no slice missing
(a gap of two or more steps is refused). A series whose slice origins do not step along
``n`` (gantry tilt) or whose gaps differ (e.g. 4 mm slices followed by 7 mm ones) is
resampled onto a regular grid in the slices' own frame: axes row, column and ``n``, the
in-plane spacing kept, the slice spacing the median gap (adjusted so that the first and
last slices stay where they are). Each output plane lies between two acquired slices and
takes their values, bilinearly shifted by each slice's in-plane offset and linearly
weighted by distance along ``n``; voxels no slice covers get the series' minimum. The
volume's metadata (``slice_geometry``) says what was found and done.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pydicom

from .. import limits as L
from ..dicomio import decode_frames, floats_tag, is_non_image, looks_like_dicom, read_dataset
from ..errors import InputError
from ..inputpaths import folder_files

__all__ = ["read_dicom_series"]

#: In-plane offset (mm) between slice origins beyond which a series counts as tilted.
TILT_OFFSET_MM = 0.01
#: HU given to padding pixels (PixelPaddingValue: outside the scanned field): air.
PADDING_HU = -1024.0


def _series_headers(folder: Path) -> dict[str, list[tuple[Path, pydicom.Dataset]]]:
    """Image headers of ``folder`` grouped by SeriesInstanceUID. Files that are not meant to be DICOM
    (a README) and DICOM files of a known non-image class are skipped; a DICOM file that cannot be read
    or has no image is refused (a slice dropped silently would shift the whole volume)."""
    series: dict[str, list[tuple[Path, pydicom.Dataset]]] = {}
    for f in folder_files(folder, "CT series"):
        try:
            ds = read_dataset(f, stop_before_pixels=True)
        except InputError as exc:
            if "is not a DICOM file" in str(exc) and not looks_like_dicom(f):
                continue
            raise
        if "Rows" in ds or "PixelData" in ds or "ImagePositionPatient" in ds:
            series.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((f, ds))
        elif not is_non_image(ds):
            raise InputError(f"{f.name} is a DICOM file without image data: it is truncated or damaged; copy the series again")
    return series


def _vector(ds: pydicom.Dataset, keyword: str, n: int, f: Path) -> np.ndarray:
    values = floats_tag(ds, keyword, f.name)
    if values is None or len(values) != n:
        raise InputError(f"{f.name} has no readable {keyword} ({n} numbers): the slice cannot be placed; the series is "
                         "truncated or damaged; copy it again or export it as NIfTI/NRRD")
    return np.asarray(values, dtype=float)


def _geometry(headers: list[tuple[Path, pydicom.Dataset]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """Row and column directions, normal, positions (LPS mm, per slice) and (row, column) spacing."""
    first_f, first = headers[0]
    orient = _vector(first, "ImageOrientationPatient", 6, first_f)
    spacing = _vector(first, "PixelSpacing", 2, first_f)
    shape = (int(first.get("Rows", 0)), int(first.get("Columns", 0)))
    row, col = orient[:3], orient[3:]
    if abs(np.linalg.norm(row) - 1) > 1e-2 or abs(np.linalg.norm(col) - 1) > 1e-2 or abs(row @ col) > 1e-2:
        raise InputError(f"{first_f.name} has ImageOrientationPatient {orient.tolist()}: not two orthogonal unit vectors; "
                         "the series is damaged")
    row, col = row / np.linalg.norm(row), col / np.linalg.norm(col)
    positions = []
    for f, ds in headers:
        if np.abs(_vector(ds, "ImageOrientationPatient", 6, f) - orient).max() > L.SLICE_ORIENTATION_TOLERANCE:
            raise InputError(f"{f.name} is oriented differently from {first_f.name}: the folder holds more than one stack; "
                             "put one series (one orientation) in a folder of its own")
        if np.abs(_vector(ds, "PixelSpacing", 2, f) - spacing).max() > 1e-6 or (int(ds.get("Rows", 0)), int(ds.get("Columns", 0))) != shape:
            raise InputError(f"{f.name} has another matrix or pixel spacing than {first_f.name}: the series mixes "
                             "acquisitions; export it again")
        positions.append(_vector(ds, "ImagePositionPatient", 3, f))
    spacing_t = (float(spacing[0]), float(spacing[1]))
    if not all(L.CTA_VOXEL_SIZE_MM[0] <= s <= L.CTA_VOXEL_SIZE_MM[1] for s in spacing_t):
        raise InputError(f"{first_f.name} has PixelSpacing {spacing_t} mm: outside {L.CTA_VOXEL_SIZE_MM[0]:g}..{L.CTA_VOXEL_SIZE_MM[1]:g} mm; "
                         "the series is damaged")
    return row, col, np.cross(row, col), np.asarray(positions), spacing_t


def _check_gaps(depths: np.ndarray, names: list[str]) -> tuple[float, bool]:
    """(median gap, even?) of sorted slice depths; refuses duplicates and missing slices."""
    gaps = np.diff(depths)
    if len(gaps) == 0:
        raise InputError(f"the series has one slice ({names[0]}): a CTA is a 3D stack; point to the folder of all its slices")
    if np.all(np.abs(depths - depths[0]) < L.SLICE_GAP_TOLERANCE_MM):
        raise InputError(f"all {len(depths)} slices of the series sit at the same position along the slice normal: "
                         "the positions (ImagePositionPatient) are damaged or the files are not one stack; export the series again")
    median = float(np.median(gaps))
    tol = max(L.SLICE_GAP_TOLERANCE_MM, L.SLICE_GAP_TOLERANCE * median)
    same = np.nonzero(gaps < tol)[0]
    if len(same):
        k = int(same[0])
        raise InputError(f"slices {names[k]} and {names[k + 1]} sit {gaps[k]:.3g} mm apart (the series steps {median:.4g} mm): "
                         "two acquisitions in one folder, or duplicated files; keep one series per folder")
    if np.all(np.abs(gaps - median) <= tol):
        return median, True
    steps = gaps / median
    if np.all(np.abs(steps - np.round(steps)) * median <= tol):
        k = int(np.argmax(steps))
        missing = int(np.round(steps).sum() - len(gaps))
        raise InputError(f"{missing} slice(s) missing from the series: {names[k]} and {names[k + 1]} are {gaps[k]:.4g} mm apart "
                         f"where the series steps {median:.4g} mm; copy the complete series again")
    return median, False


def _shifted(plane: np.ndarray, di: float, dj: float, shape: tuple[int, int], fill: float) -> np.ndarray:
    """``plane`` sampled bilinearly at (row j - dj, column i - di) for every output pixel (j, i); ``fill`` outside."""
    rows, cols = shape
    h, w = plane.shape
    out = np.zeros(shape, dtype=np.float64)
    j0, i0 = math.floor(-dj), math.floor(-di)
    fj, fi = -dj - j0, -di - i0
    jj = np.arange(rows)[:, None] + j0
    ii = np.arange(cols)[None, :] + i0
    for oj, wj in ((0, 1 - fj), (1, fj)):
        for oi, wi in ((0, 1 - fi), (1, fi)):
            if wj * wi == 0:
                continue
            r, c = jj + oj, ii + oi
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            out += wj * wi * np.where(inside, plane[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], fill)
    return out


def _regularise(
    planes: np.ndarray, depths: np.ndarray, offsets: np.ndarray, step: float, spacing: tuple[float, float]
) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Planes (sorted by depth, in-plane offsets (along row dir, along column dir) in mm from the first
    slice) on a regular grid: the volume, its slice spacing and the pixel offset (i0, j0) of its first voxel."""
    n_out = max(2, int(round((depths[-1] - depths[0]) / step)) + 1)
    dz = (depths[-1] - depths[0]) / (n_out - 1)
    di, dj = offsets[:, 0] / spacing[1], offsets[:, 1] / spacing[0]
    h, w = planes.shape[1:]
    hi = L.CTA_VOXELS_PER_AXIS[1]
    if n_out > hi or max(abs(di).max(), abs(dj).max()) > hi or depths[-1] - depths[0] > L.CTA_EXTENT_MM[1]:
        raise InputError(f"the slice positions span {depths[-1] - depths[0]:.4g} mm with in-plane shifts up to "
                         f"{max(abs(offsets).max(), 0):.4g} mm: no plausible CT; ImagePositionPatient is damaged")
    i0, j0 = math.floor(di.min()), math.floor(dj.min())
    shape = (h + math.ceil(dj.max()) - j0, w + math.ceil(di.max()) - i0)
    voxels = n_out * shape[0] * shape[1]
    if shape[0] > hi or shape[1] > hi or voxels > L.CTA_MAX_VOXELS or voxels > L.CTA_RESAMPLE_MAX_GROWTH * planes.size:
        raise InputError(f"resampling the series would need {n_out} x {shape[0]} x {shape[1]} voxels from {planes.shape[0]} x "
                         f"{planes.shape[1]} x {planes.shape[2]} acquired (at most {L.CTA_RESAMPLE_MAX_GROWTH} times as many): "
                         "the slice positions (ImagePositionPatient) or spacings are damaged; export the series again")
    fill = float(planes.min())
    out = np.empty((n_out,) + shape, dtype=np.float32)
    for t in range(n_out):
        z = depths[0] + t * dz
        b = int(np.clip(np.searchsorted(depths, z, side="right"), 1, len(depths) - 1))
        a = b - 1
        wb = float(np.clip((z - depths[a]) / (depths[b] - depths[a]), 0.0, 1.0))
        plane = np.zeros(shape, dtype=np.float64)
        for k, weight in ((a, 1.0 - wb), (b, wb)):
            if weight > 0:
                plane += weight * _shifted(planes[k], di[k] - i0, dj[k] - j0, shape, fill)
        out[t] = plane
    return out, dz, (i0, j0)


def _ids(ds: pydicom.Dataset) -> dict[str, str]:
    """PatientID, StudyInstanceUID and SeriesInstanceUID of a slice, those present."""
    return {k: str(ds.get(k)) for k in ("PatientID", "StudyInstanceUID", "SeriesInstanceUID") if ds.get(k) not in (None, "")}


def read_dicom_series(folder: Path, series_uid: str | None) -> tuple[np.ndarray, np.ndarray, list[Path], dict]:
    """Voxels ``[k, j, i]`` (HU, float32), ``ijk -> LPS`` 4x4, the files in slice order and
    ``slice_geometry`` notes of the series in ``folder`` (``series_uid`` picks one of several)."""
    groups = _series_headers(folder)
    if not groups:
        raise InputError(f"{folder} holds no DICOM series: point to a folder of CT slices or to a NIfTI/NRRD/MHA file")
    ids = sorted(groups)
    if series_uid is None:
        if len(ids) > 1:
            raise InputError(f"{folder} holds {len(ids)} DICOM series ({', '.join(ids)}): choose one with --cta-series-uid UID "
                             "(Python: load_cta(..., series_uid=UID)) or put the CTA series in a folder of its own")
        series_uid = ids[0]
    elif series_uid not in groups:
        raise InputError(f"series {series_uid} is not in {folder}; it holds {', '.join(ids)}: give one of them to --cta-series-uid")
    headers = groups[series_uid]
    lo, hi = L.CTA_VOXELS_PER_AXIS
    if not lo <= len(headers) <= hi:
        raise InputError(f"{folder} holds {len(headers)} slices of series {series_uid}: a CTA has {lo}..{hi}; "
                         "point to the folder of the complete series")
    row, col, normal, positions, spacing = _geometry(headers)
    depths = positions @ normal
    order = np.argsort(depths, kind="stable")
    headers = [headers[k] for k in order]
    positions, depths = positions[order], depths[order]
    names = [f.name for f, _ in headers]
    step, even = _check_gaps(depths, names)
    rel = positions - positions[0]
    offsets = np.stack([rel @ row, rel @ col], axis=1)  # in-plane offset of each slice origin (mm)
    tilted = bool(np.abs(offsets).max() > TILT_OFFSET_MM)

    rows, cols = int(headers[0][1].get("Rows", 0)), int(headers[0][1].get("Columns", 0))  # all equal (_geometry)

    def check(shape: tuple[int, int, int]) -> None:
        if not (lo <= shape[1] <= hi and lo <= shape[2] <= hi) or shape != (1, rows, cols):
            raise InputError(f"{folder.name}: a slice declares {shape[0]} frame(s) of {shape[1]} x {shape[2]} pixels: a CT slice "
                             f"of this series is one frame of {rows} x {cols} pixels ({lo}..{hi} per side)")

    if len(headers) * rows * cols > L.CTA_MAX_VOXELS:
        raise InputError(f"{folder.name}: {len(headers)} slices of {rows} x {cols} pixels are more than the {L.CTA_MAX_VOXELS} "
                         "voxels a CTA may have here; give a smaller series (or crop it to the head)")
    planes = np.empty((len(headers), rows, cols), dtype=np.float32)
    padded = 0
    for k, (f, _) in enumerate(headers):
        frames, slice_notes = decode_frames(read_dataset(f), f.name, check, padding_value=PADDING_HU)
        planes[k] = frames[0]
        padded += slice_notes.get("pixel_padding", {}).get("pixels", 0)
    ijk_to_lps = np.eye(4)
    notes: dict = {"slice_geometry": {"slices": len(headers), "median_gap_mm": float(step)}, "dicom_ids": _ids(headers[0][1])}
    if padded:
        notes["pixel_padding"] = {"voxels": int(padded), "set_to_hu": PADDING_HU,
                                  "why": "PixelPaddingValue marks pixels outside the scanned field"}
    if even and not tilted:
        ijk_to_lps[:3, :3] = np.stack([row * spacing[1], col * spacing[0], normal * step], axis=1)
        ijk_to_lps[:3, 3] = positions[0]
        notes["slice_geometry"]["resampled"] = False
        return planes, ijk_to_lps, [f for f, _ in headers], notes
    array, dz, (i0, j0) = _regularise(planes, depths, offsets, step, spacing)
    ijk_to_lps[:3, :3] = np.stack([row * spacing[1], col * spacing[0], normal * dz], axis=1)
    ijk_to_lps[:3, 3] = positions[0] + i0 * spacing[1] * row + j0 * spacing[0] * col
    stack = positions[-1] - positions[0]
    tilt_deg = math.degrees(math.acos(min(1.0, abs(stack @ normal) / np.linalg.norm(stack))))
    notes["slice_geometry"].update(
        resampled=True,
        reason=", ".join(r for r, on in (("gantry tilt", tilted), ("uneven slice positions", not even)) if on),
        gantry_tilt_deg=round(tilt_deg, 3),
        slice_gaps_mm=[round(float(g), 4) for g in np.diff(depths)],
        slice_spacing_mm=float(dz),
        method="planes along the slice normal, bilinear in-plane shift of each slice's offset, linear between the two nearest "
               "slices; uncovered voxels = the series minimum",
    )
    return array, ijk_to_lps, [f for f, _ in headers], notes
