"""Readers for DSA runs: DICOM XA multi-frame, a folder of single-frame DICOMs, and
NIfTI/NRRD 2D+time images with a JSON geometry sidecar.

Geometry from DICOM:

* ``pixel_spacing_mm`` = ImagerPixelSpacing (detector plane, [row, col]); without it,
  PixelSpacing x EstimatedRadiographicMagnificationFactor (PixelSpacing is calibrated
  at the patient); PixelSpacing alone is taken as detector-plane spacing (recorded in
  ``metadata['geometry_sources']``).
* ``principal_offset_mm``: DetectorActiveOrigin ``(r0, c0)`` mm is the top-left of the
  imaged area on the physical detector. With PhysicalDetectorSize ``(Hp, Wp)`` and the
  imaged size ``(h, w)`` (DetectorActiveDimensions, else rows x spacing), the image
  centre lies ``d = (r0 + h/2 - Hp/2, c0 + w/2 - Wp/2)`` (down, right) from the
  detector centre, which the central ray is assumed to hit; so the camera offset is
  ``(x0, y0) = (-d_col, -d_row)`` (camera x grows towards column 0, y towards row 0).
  Without PhysicalDetectorSize the offset is 0 (noted in metadata).
* Frames: the pixel data with the linear modality LUT (RescaleSlope/Intercept) when
  present; no inversion (see :meth:`DSARun.attenuation`).

Every geometry value can be overridden by keyword (see ``run.GEOMETRY_KEYS``).
"""

from __future__ import annotations

import json
import math
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pydicom
import SimpleITK as sitk
from pydicom.errors import InvalidDicomError

from ..cta.io import file_sha256
from ..geometry.detector import CArmAngles, Detector
from .run import GEOMETRY_KEYS, GEOMETRY_SOURCES, REQUIRED_GEOMETRY_KEYS, DSAInputError, DSARun, cli_option

__all__ = ["read_dsa", "run_from_geometry", "sidecar_path", "NIFTI_EXTENSIONS", "SIDECAR_KEYS"]

NIFTI_EXTENSIONS = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")
#: JSON sidecar keys: the geometry keys plus the photometric interpretation of the stored frames.
SIDECAR_KEYS = GEOMETRY_KEYS + ("photometric_interpretation",)
#: Largest angle difference (deg) tolerated between single-frame files of one run.
ANGLE_TOLERANCE_DEG = 0.5


def _ext(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def sidecar_path(image_path: str | Path) -> Path:
    """``run.nii.gz`` -> ``run.json`` (the geometry sidecar beside a NIfTI/NRRD/MHA run)."""
    p = Path(image_path)
    stem = p.name[: -len(_ext(p))]
    return p.with_name(stem + ".json")


def _pair(value: Any, key: str) -> tuple[float, float]:
    v = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    if v.size == 1:
        v = np.repeat(v, 2)
    if v.size != 2:
        raise DSAInputError(f"{key} needs one or two numbers (row, col), got {value!r}")
    return (float(v[0]), float(v[1]))


def _normalise(key: str, value: Any) -> Any:
    if key in ("pixel_spacing_mm", "principal_offset_mm"):
        return _pair(value, key)
    try:
        return float(value)
    except (TypeError, ValueError):
        raise DSAInputError(f"{key} must be a number, got {value!r}") from None


def _assemble(
    frames: np.ndarray,
    found: dict[str, Any],
    sources: dict[str, str],
    overrides: dict[str, Any],
    name: str,
    where: Callable[[str], str],
    metadata: dict,
) -> DSARun:
    """Merge file values with overrides, report every missing required key at once, build the run."""
    unknown = sorted(set(overrides) - set(GEOMETRY_KEYS))
    if unknown:
        raise DSAInputError(f"unknown geometry override(s) {unknown}; valid keys: {', '.join(GEOMETRY_KEYS)}")
    values = {k: _normalise(k, v) for k, v in found.items() if v is not None}
    for key, value in overrides.items():
        if value is not None:
            values[key] = _normalise(key, value)
            sources[key] = "override"
    missing = [k for k in REQUIRED_GEOMETRY_KEYS if k not in values]
    if missing:
        lines = []
        for key in missing:
            example = "ROW COL" if key == "pixel_spacing_mm" else "..."
            lines.append(f"{where(key)} is missing in {name}: pass {key}=... (CLI: {cli_option(key)} {example})")
        raise DSAInputError("; ".join(lines))
    spacing = values["pixel_spacing_mm"]
    for key in ("sid_mm", "sod_mm"):
        if not (math.isfinite(values[key]) and values[key] > 0):
            raise DSAInputError(f"{key} must be a positive distance in mm, got {values[key]} ({sources.get(key, where(key))})")
    if not values["sod_mm"] < values["sid_mm"]:
        raise DSAInputError(
            f"source-to-isocentre distance {values['sod_mm']} mm is not shorter than the source-to-detector distance "
            f"{values['sid_mm']} mm in {name}: check sod_mm / sid_mm"
        )
    if min(spacing) <= 0 or not all(map(math.isfinite, spacing)):
        raise DSAInputError(f"pixel_spacing_mm must be positive mm, got {spacing}")
    t, h, w = frames.shape
    detector = Detector(h, w, spacing, values["sid_mm"], values.get("principal_offset_mm", (0.0, 0.0)))
    angles = CArmAngles(values["primary_deg"], values["secondary_deg"], values["sid_mm"], values["sod_mm"])
    metadata["geometry_sources"] = {k: sources.get(k, "file") for k in values}
    return DSARun(frames, detector, angles, values.get("frame_time_ms"), metadata)


def run_from_geometry(
    frames: np.ndarray, geometry: dict[str, Any], *, name: str, source: str, metadata: dict | None = None
) -> DSARun:
    """A run from frames ``(T, H, W)`` and geometry values (``GEOMETRY_KEYS`` names, mm / deg) that
    did not come from a file (e.g. a Slicer node's attributes): the same checks as the file readers.
    ``name`` names the input in messages, ``source`` is recorded as every value's origin."""
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.ndim != 3:
        raise DSAInputError(f"{name}: DSA frames must be (T, H, W), got shape {frames.shape}")
    unknown = sorted(set(geometry) - set(GEOMETRY_KEYS))
    if unknown:
        raise DSAInputError(f"{name}: unknown geometry key(s) {unknown}; valid keys: {', '.join(GEOMETRY_KEYS)}")
    found = {k: v for k, v in geometry.items() if v is not None}
    return _assemble(frames, found, {k: source for k in found}, {}, name, lambda k: f"'{k}'", dict(metadata or {}))


# ------------------------------------------------------------------------- DICOM


def _num(ds: pydicom.Dataset, keyword: str) -> float | None:
    value = ds.get(keyword)
    if value is None or value == "":
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _nums(ds: pydicom.Dataset, keyword: str) -> list[float] | None:
    value = ds.get(keyword)
    if value is None or value == "":
        return None
    try:
        return [float(v) for v in (value if isinstance(value, (list, pydicom.multival.MultiValue)) else [value])]
    except (TypeError, ValueError):
        return None


def _dicom_geometry(ds: pydicom.Dataset, rows: int, cols: int) -> tuple[dict, dict, dict]:
    """Geometry values, their sources and notes from one DICOM dataset."""
    found: dict[str, Any] = {
        "primary_deg": _num(ds, "PositionerPrimaryAngle"),
        "secondary_deg": _num(ds, "PositionerSecondaryAngle"),
        "sid_mm": _num(ds, "DistanceSourceToDetector"),
        "sod_mm": _num(ds, "DistanceSourceToPatient"),
    }
    sources = {k: GEOMETRY_SOURCES[k].split(" (")[0] for k, v in found.items() if v is not None}
    notes: dict[str, str] = {}
    imager = _nums(ds, "ImagerPixelSpacing")
    pixel = _nums(ds, "PixelSpacing")
    magnification = _num(ds, "EstimatedRadiographicMagnificationFactor")
    if imager:
        found["pixel_spacing_mm"], sources["pixel_spacing_mm"] = imager, "ImagerPixelSpacing"
    elif pixel and magnification:
        found["pixel_spacing_mm"] = [p * magnification for p in pixel]
        sources["pixel_spacing_mm"] = "PixelSpacing x EstimatedRadiographicMagnificationFactor"
    elif pixel:
        found["pixel_spacing_mm"], sources["pixel_spacing_mm"] = pixel, "PixelSpacing (taken as detector plane)"
    frame_time = _num(ds, "FrameTime")
    vector = _nums(ds, "FrameTimeVector")
    if frame_time:
        found["frame_time_ms"], sources["frame_time_ms"] = frame_time, "FrameTime"
    elif vector and len(vector) > 1:
        found["frame_time_ms"], sources["frame_time_ms"] = float(np.mean(vector[1:])), "FrameTimeVector (mean)"
    origin = _nums(ds, "DetectorActiveOrigin")
    if origin and len(origin) == 2 and found.get("pixel_spacing_mm"):
        physical = _nums(ds, "PhysicalDetectorSize")
        active = _nums(ds, "DetectorActiveDimensions")
        spacing = _pair(found["pixel_spacing_mm"], "pixel_spacing_mm")
        if physical and len(physical) == 2:
            h, w = active if active and len(active) == 2 else (rows * spacing[0], cols * spacing[1])
            d_row = origin[0] + h / 2 - physical[0] / 2
            d_col = origin[1] + w / 2 - physical[1] / 2
            found["principal_offset_mm"] = (-d_col, -d_row)
            sources["principal_offset_mm"] = "DetectorActiveOrigin + PhysicalDetectorSize"
        else:
            notes["principal_offset"] = "DetectorActiveOrigin ignored: PhysicalDetectorSize (0018,9429) is missing"
    return found, sources, notes


def _dicom_metadata(ds: pydicom.Dataset, path: Path, files: list[Path]) -> dict:
    meta = {
        "source_path": str(path.resolve()),
        "source_files": len(files),
        "sha256": file_sha256(files),
        "photometric_interpretation": str(ds.get("PhotometricInterpretation", "MONOCHROME2")),
        "bits_stored": int(ds.get("BitsStored", 0) or 0),
        "transfer_syntax": str(ds.file_meta.get("TransferSyntaxUID", "")) if hasattr(ds, "file_meta") else "",
    }
    for key in ("PatientID", "StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "SOPClassUID", "Modality", "SeriesDescription"):
        if ds.get(key) not in (None, ""):
            meta[key] = str(ds.get(key))
    return meta


def _pixels(ds: pydicom.Dataset, name: str) -> np.ndarray:
    """Decoded frames ``(T, H, W)`` float32 with the linear modality LUT applied."""
    if int(ds.get("SamplesPerPixel", 1) or 1) != 1:
        raise DSAInputError(f"{name} is a colour image (SamplesPerPixel {ds.SamplesPerPixel}): export the run as greyscale")
    try:
        array = ds.pixel_array
    except Exception as exc:  # decoders raise many types (RuntimeError, NotImplementedError, ValueError)
        syntax = ds.file_meta.get("TransferSyntaxUID", "unknown") if hasattr(ds, "file_meta") else "unknown"
        raise DSAInputError(
            f"cannot decode the pixel data of {name} (transfer syntax {getattr(syntax, 'name', syntax)}: {exc}); "
            "install the pylibjpeg plugins (pip install pylibjpeg pylibjpeg-libjpeg pylibjpeg-openjpeg pylibjpeg-rle) "
            "or decompress the file (e.g. gdcmconv --raw)"
        ) from None
    frames_declared = int(ds.get("NumberOfFrames", 1) or 1)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[0] != frames_declared:
        raise DSAInputError(f"{name}: decoded pixel data has shape {array.shape}, expected {frames_declared} greyscale frames")
    frames = array.astype(np.float32)
    slope, intercept = _num(ds, "RescaleSlope"), _num(ds, "RescaleIntercept")
    if slope is not None or intercept is not None:
        frames = frames * np.float32(1.0 if slope is None else slope) + np.float32(intercept or 0.0)
    return frames


def _read_dicom_file(path: Path, overrides: dict) -> DSARun:
    try:
        ds = pydicom.dcmread(path)
    except InvalidDicomError:
        raise DSAInputError(f"{path} is not a DICOM file: give an XA multi-frame DICOM, a folder of frames or a NIfTI/NRRD run") from None
    if "PixelData" not in ds:
        raise DSAInputError(f"{path.name} holds no pixel data (a report or structure?): give the image file of the run")
    frames = _pixels(ds, path.name)
    found, sources, notes = _dicom_geometry(ds, frames.shape[1], frames.shape[2])
    meta = _dicom_metadata(ds, path, [path])
    meta.update(notes)
    return _assemble(frames, found, sources, overrides, path.name, lambda k: GEOMETRY_SOURCES[k], meta)


def _dicom_time_s(ds: pydicom.Dataset) -> float | None:
    for key in ("AcquisitionTime", "ContentTime"):
        value = str(ds.get(key, "") or "")
        if value:
            for fmt in ("%H%M%S.%f", "%H%M%S"):
                try:
                    t = datetime.strptime(value.strip(), fmt)
                    return t.hour * 3600 + t.minute * 60 + t.second + t.microsecond / 1e6
                except ValueError:
                    continue
    return None


def _read_dicom_folder(folder: Path, overrides: dict) -> DSARun:
    headers: list[tuple[Path, pydicom.Dataset]] = []
    for f in sorted(p for p in folder.iterdir() if p.is_file()):
        try:
            headers.append((f, pydicom.dcmread(f, stop_before_pixels=True)))
        except (InvalidDicomError, OSError):
            continue
    headers = [(f, ds) for f, ds in headers if "Rows" in ds]
    if not headers:
        raise DSAInputError(f"{folder} holds no DICOM images: point to the folder of the run's frames or to its file")
    multi = [f for f, ds in headers if int(ds.get("NumberOfFrames", 1) or 1) > 1]
    if len(headers) == 1 or multi:
        if len(headers) == 1:
            return _read_dicom_file(headers[0][0], overrides)
        raise DSAInputError(f"{folder} mixes {len(multi)} multi-frame file(s) with other images: pass the run's file itself")
    series = {str(ds.get("SeriesInstanceUID", "")) for _, ds in headers}
    if len(series) > 1:
        raise DSAInputError(f"{folder} holds {len(series)} series: put one run's frames in a folder of their own")
    headers.sort(key=lambda fd: (int(fd[1].get("InstanceNumber", 0) or 0), _dicom_time_s(fd[1]) or 0.0, fd[0].name))
    first = headers[0][1]
    for f, ds in headers[1:]:
        for key in ("PositionerPrimaryAngle", "PositionerSecondaryAngle"):
            a, b = _num(first, key), _num(ds, key)
            if a is not None and b is not None and abs(a - b) > ANGLE_TOLERANCE_DEG:
                raise DSAInputError(f"{f.name} has {key} {b} but the first frame {a}: the folder is not one fixed-angle run")
    datasets = [pydicom.dcmread(f) for f, _ in headers]
    frames = np.concatenate([_pixels(ds, f.name) for (f, _), ds in zip(headers, datasets)])
    found, sources, notes = _dicom_geometry(first, frames.shape[1], frames.shape[2])
    if "frame_time_ms" not in sources:
        times = [t for t in (_dicom_time_s(ds) for _, ds in headers) if t is not None]
        if len(times) == len(headers) > 1 and np.all(np.diff(times) > 0):
            found["frame_time_ms"] = float(np.median(np.diff(times)) * 1000.0)
            sources["frame_time_ms"] = "AcquisitionTime/ContentTime differences"
    meta = _dicom_metadata(first, folder, [f for f, _ in headers])
    meta.update(notes)
    return _assemble(frames, found, sources, overrides, folder.name, lambda k: GEOMETRY_SOURCES[k], meta)


# ---------------------------------------------------------------- NIfTI + sidecar


def _read_image_with_sidecar(path: Path, overrides: dict) -> DSARun:
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no detail"
        raise DSAInputError(f"cannot read {path} as an image ({detail}): check the file") from None
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise DSAInputError(f"{path.name} has {image.GetNumberOfComponentsPerPixel()} components per pixel: store greyscale frames")
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    if image.GetDimension() == 4 and array.shape[1] == 1:  # (T, 1, H, W): 2D+time stored as 4D
        array = array[:, 0]
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3:
        raise DSAInputError(f"{path.name} has size {image.GetSize()}: a DSA run is 2D+time (columns, rows, frames)")
    side = sidecar_path(path)
    found: dict[str, Any] = {}
    if side.exists():
        try:
            found = json.loads(side.read_text())
        except json.JSONDecodeError as exc:
            raise DSAInputError(f"{side.name} is not valid JSON ({exc}): fix the sidecar") from None
        if not isinstance(found, dict):
            raise DSAInputError(f"{side.name} must hold a JSON object with keys {', '.join(SIDECAR_KEYS)}")
        unknown = sorted(set(found) - set(SIDECAR_KEYS))
        if unknown:
            raise DSAInputError(f"{side.name} has unknown key(s) {unknown}; valid keys: {', '.join(SIDECAR_KEYS)}")
    photometric = str(found.pop("photometric_interpretation", "MONOCHROME2"))
    if photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise DSAInputError(f"photometric_interpretation in {side.name} must be MONOCHROME1 or MONOCHROME2, got {photometric!r}")
    sources = {k: side.name for k in found}
    files = [path] + ([side] if side.exists() else [])
    meta = {
        "source_path": str(path.resolve()),
        "source_files": len(files),
        "sha256": file_sha256(files),
        "photometric_interpretation": photometric,
    }
    def where(key: str) -> str:
        return f"'{key}' (sidecar {side.name})"

    return _assemble(array, found, sources, overrides, path.name, where, meta)


def read_dsa(path: str | Path, **overrides: Any) -> DSARun:
    """Read a DSA run from a DICOM file (XA multi-frame or single frame; uncompressed,
    JPEG Baseline/Lossless, JPEG 2000 or RLE), a folder of single-frame DICOMs (sorted
    by InstanceNumber then acquisition time) or a NIfTI/NRRD/MHA 2D+time image with a
    ``<name>.json`` geometry sidecar. Keyword overrides (``primary_deg``, ``secondary_deg``,
    ``sid_mm``, ``sod_mm``, ``pixel_spacing_mm`` (row, col) or one value,
    ``principal_offset_mm`` (x0, y0), ``frame_time_ms``) replace file values; ``None``
    leaves the file value. A missing required value raises :class:`DSAInputError`
    naming the tag/key and the override.
    """
    path = Path(path)
    if not path.exists():
        raise DSAInputError(f"DSA run not found: {path} (check the path)")
    if path.is_dir():
        return _read_dicom_folder(path, overrides)
    if _ext(path) in NIFTI_EXTENSIONS:
        return _read_image_with_sidecar(path, overrides)
    return _read_dicom_file(path, overrides)
