"""Readers for DSA runs: DICOM XA multi-frame, a folder of single-frame DICOMs, and
NIfTI/NRRD 2D+time images with a JSON geometry sidecar.

Geometry from DICOM:

* ``pixel_spacing_mm`` = ImagerPixelSpacing (detector plane, [row, col]); without it,
  PixelSpacing x EstimatedRadiographicMagnificationFactor (PixelSpacing is calibrated
  at the patient); PixelSpacing alone is taken as detector-plane spacing; without
  both, FieldOfViewDimensions (mm, [row, col] or a diameter) or IntensifierSize (a
  diameter) over the matrix (GE systems: 200 mm / 512 px = 0.390625 mm). The source
  is recorded in ``metadata['geometry_sources']``.
* ``principal_offset_mm``: DetectorActiveOrigin ``(r0, c0)`` mm is the top-left of the
  imaged area on the physical detector. With PhysicalDetectorSize ``(Hp, Wp)`` and the
  imaged size ``(h, w)`` (DetectorActiveDimensions, else rows x spacing), the image
  centre lies ``d = (r0 + h/2 - Hp/2, c0 + w/2 - Wp/2)`` (down, right) from the
  detector centre, which the central ray is assumed to hit; so the camera offset is
  ``(x0, y0) = (-d_col, -d_row)`` (camera x grows towards column 0, y towards row 0).
  Without PhysicalDetectorSize the offset is 0 (noted in metadata).
* Frames: the pixel data with the linear modality LUT (RescaleSlope/Intercept) when
  present, decoded and checked by :mod:`geopose.dicomio`; no inversion (see
  :meth:`DSARun.attenuation`). A run that declares MONOCHROME1 but whose frames look like
  MONOCHROME2 (the border, usually air, brighter than the centre as stored) is refused
  unless ``photometric_interpretation`` is given.
* A native run (every frame a plain radiograph) whose Mask Subtraction Sequence prescribes a mask (AVG_SUB) is
  subtracted as it says (:mod:`geopose.dsa.subtraction`; ``metadata['subtraction']`` says how).

Every geometry value can be overridden by keyword (see ``run.GEOMETRY_KEYS``). Every
reader, and :func:`run_from_geometry` for runs that come from no file, ends in the same
checks (:func:`geopose.dsa.run.check_geometry`: plausibility bounds, angles wrapped to
(-180, 180]).
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pydicom
import SimpleITK as sitk

from .. import limits as L
from ..checksums import file_sha256
from ..dicomio import decode_frames, float_tag, floats_tag, int_tag, looks_like_dicom, raw_tag, read_dataset
from ..errors import InputError
from ..geometry.detector import CArmAngles, Detector
from ..inputpaths import folder_files, input_kind
from ..imagefiles import IMAGE_EXTENSIONS, check_image_file, image_extension
from ..jsonio import read_json
from .run import (
    GEOMETRY_KEYS, GEOMETRY_SOURCES, PHOTOMETRIC, REQUIRED_GEOMETRY_KEYS, DSARun, check_frames_shape, check_geometry, cli_hint,
)
from .subtraction import read_mask_subtraction, subtract_mask

__all__ = ["read_dsa", "run_from_geometry", "sidecar_path", "NIFTI_EXTENSIONS", "SIDECAR_KEYS"]

NIFTI_EXTENSIONS = IMAGE_EXTENSIONS
#: JSON sidecar keys: the geometry keys plus the photometric interpretation of the stored frames.
SIDECAR_KEYS = GEOMETRY_KEYS + ("photometric_interpretation",)
#: Largest angle difference (deg) tolerated between single-frame files of one run.
ANGLE_TOLERANCE_DEG = 0.5
#: A MONOCHROME1 run "looks like MONOCHROME2" when its mean frame's border is brighter than its
#: centre (as stored) by more than this fraction of the 1-99 percentile range.
PHOTOMETRIC_MARGIN = 0.05


def sidecar_path(image_path: str | Path) -> Path:
    """``run.nii.gz`` -> ``run.json`` (the geometry sidecar beside a NIfTI/NRRD/MHA run)."""
    p = Path(image_path)
    stem = p.name[: -len(image_extension(p))]
    return p.with_name(stem + ".json")


def _number(value: Any, origin: str) -> float:
    if isinstance(value, (bool, dict, list, tuple)) or value is None:
        raise InputError(f"{origin} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{origin} must be a number, got {str(value)[:60]!r}") from None


def _normalise(key: str, value: Any, origin: str) -> Any:
    """A scalar key as float; ``pixel_spacing_mm`` / ``principal_offset_mm`` as a (row, col) / (x0, y0) pair."""
    if key not in ("pixel_spacing_mm", "principal_offset_mm"):
        return _number(value, origin)
    items = list(value) if isinstance(value, (list, tuple, np.ndarray, pydicom.multival.MultiValue)) else [value]
    if len(items) == 1 and key == "pixel_spacing_mm":
        items = items * 2
    if len(items) != 2:
        raise InputError(f"{origin} needs {'one or ' if key == 'pixel_spacing_mm' else ''}two numbers "
                         f"{'(row, col)' if key == 'pixel_spacing_mm' else '(x0, y0)'}, got {str(value)[:60]!r}")
    return tuple(_number(v, origin) for v in items)


def _assemble(
    frames: np.ndarray,
    found: dict[str, Any],
    sources: dict[str, str],
    overrides: dict[str, Any],
    name: str,
    where: Callable[[str], str],
    metadata: dict,
) -> DSARun:
    """Merge file values with overrides, report every missing required key at once, check, build the run."""
    unknown = sorted(set(overrides) - set(GEOMETRY_KEYS))
    if unknown:
        raise InputError(f"unknown geometry override(s) {unknown}; valid keys: {', '.join(GEOMETRY_KEYS)}")
    for key, value in overrides.items():
        if value is not None:
            found[key] = value
            sources[key] = "override"

    def origin(key: str) -> str:
        return f"the override {key}" if sources.get(key) == "override" else f"{where(key)} in {name}"

    values = {k: _normalise(k, v, origin(k)) for k, v in found.items() if v is not None}
    missing = [k for k in REQUIRED_GEOMETRY_KEYS if k not in values]
    if missing:
        lines = []
        for key in missing:
            example = "ROW COL" if key == "pixel_spacing_mm" else "..."
            lines.append(f"{where(key)} is missing in {name}: pass {key}=... (CLI: {cli_hint(key)} {example})")
        raise InputError("; ".join(lines))
    values = check_geometry(values, name, lambda k: "the override" if sources.get(k) == "override" else where(k))
    t, h, w = frames.shape
    detector = Detector(h, w, values["pixel_spacing_mm"], values["sid_mm"], values.get("principal_offset_mm", (0.0, 0.0)))
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
        raise InputError(f"{name}: DSA frames must be (T, H, W), got shape {frames.shape}")
    check_frames_shape(frames.shape, name)
    unknown = sorted(set(geometry) - set(GEOMETRY_KEYS))
    if unknown:
        raise InputError(f"{name}: unknown geometry key(s) {unknown}; valid keys: {', '.join(GEOMETRY_KEYS)}")
    found = {k: v for k, v in geometry.items() if v is not None}
    meta = dict(metadata or {})
    meta.setdefault("source_path", name)
    return _assemble(frames, found, {k: source for k in found}, {}, name, lambda k: f"'{k}'", meta)


def _check_photometric(frames: np.ndarray, photometric: str, name: str) -> None:
    """Refuse MONOCHROME1 frames whose mean frame has a border (outer tenth) brighter than its centre (inner
    half), as stored: the head would come out dark. Only a declared MONOCHROME1 is checked (the XA image module
    allows MONOCHROME2 only); a collimated MONOCHROME1 run may need the override."""
    if photometric != "MONOCHROME1":
        return
    image = frames.mean(axis=0)
    h, w = image.shape
    bh, bw = max(1, h // 10), max(1, w // 10)
    border = np.concatenate([image[:bh].ravel(), image[-bh:].ravel(), image[:, :bw].ravel(), image[:, -bw:].ravel()])
    centre = image[h // 4: h - h // 4, w // 4: w - w // 4]
    lo, hi = np.percentile(image, (1, 99))
    if np.median(border) - np.median(centre) > PHOTOMETRIC_MARGIN * max(hi - lo, 1e-12):
        raise InputError(
            f"{name} declares MONOCHROME1 but its frames look like MONOCHROME2 (the border, usually air, is brighter than "
            "the centre as stored, so the head would come out dark): fix PhotometricInterpretation in the file, or confirm "
            "the interpretation with photometric_interpretation='MONOCHROME1' or 'MONOCHROME2' (CLI: --pa-photometric / "
            "--lat-photometric)"
        )


def _photometric(declared: str, confirmed: str | None, frames: np.ndarray, name: str, metadata: dict) -> None:
    """Record the photometric interpretation: ``confirmed`` (an override) wins, else the declared one, checked."""
    if confirmed is not None:
        if confirmed not in PHOTOMETRIC:
            raise InputError(f"photometric_interpretation must be MONOCHROME1 or MONOCHROME2, got {confirmed!r}")
        metadata["photometric_interpretation"] = confirmed
        metadata["photometric_source"] = "override"
        return
    _check_photometric(frames, declared, name)
    metadata["photometric_interpretation"] = declared


# ------------------------------------------------------------------------- DICOM


def _dicom_geometry(ds: pydicom.Dataset, rows: int, cols: int, name: str) -> tuple[dict, dict, dict]:
    """Geometry values (as stored: :func:`_normalise` converts and names a damaged one), their sources
    and notes from one DICOM dataset."""
    found: dict[str, Any] = {
        "primary_deg": raw_tag(ds, "PositionerPrimaryAngle"),
        "secondary_deg": raw_tag(ds, "PositionerSecondaryAngle"),
        "sid_mm": raw_tag(ds, "DistanceSourceToDetector"),
        "sod_mm": raw_tag(ds, "DistanceSourceToPatient"),
    }
    sources = {k: GEOMETRY_SOURCES[k].split(" (")[0] for k, v in found.items() if v is not None}
    notes: dict[str, str] = {}
    imager = raw_tag(ds, "ImagerPixelSpacing")
    pixel = floats_tag(ds, "PixelSpacing", name) if imager is None else None
    fov = floats_tag(ds, "FieldOfViewDimensions", name) if imager is None and pixel is None else None
    if imager is not None:
        found["pixel_spacing_mm"], sources["pixel_spacing_mm"] = imager, "ImagerPixelSpacing"
    elif pixel:
        magnification = float_tag(ds, "EstimatedRadiographicMagnificationFactor", name)
        if magnification:
            found["pixel_spacing_mm"] = [p * magnification for p in pixel]
            sources["pixel_spacing_mm"] = "PixelSpacing x EstimatedRadiographicMagnificationFactor"
        else:
            found["pixel_spacing_mm"], sources["pixel_spacing_mm"] = pixel, "PixelSpacing (taken as detector plane)"
    elif fov and len(fov) in (1, 2):
        found["pixel_spacing_mm"] = [fov[0] / rows, fov[-1] / cols] if len(fov) == 2 else [fov[0] / max(rows, cols)] * 2
        sources["pixel_spacing_mm"] = f"FieldOfViewDimensions ({' x '.join(f'{v:g}' for v in fov)} mm) / matrix ({rows} x {cols})"
    else:
        intensifier = float_tag(ds, "IntensifierSize", name)
        if intensifier:
            found["pixel_spacing_mm"] = [intensifier / max(rows, cols)] * 2
            sources["pixel_spacing_mm"] = f"IntensifierSize ({intensifier:g} mm) / matrix ({rows} x {cols})"
    frame_time = raw_tag(ds, "FrameTime")
    if frame_time is not None and str(frame_time).strip() not in ("0", "0.0"):
        found["frame_time_ms"], sources["frame_time_ms"] = frame_time, "FrameTime"
    else:
        vector = floats_tag(ds, "FrameTimeVector", name)
        if vector and len(vector) > 1:
            found["frame_time_ms"], sources["frame_time_ms"] = float(np.mean(vector[1:])), "FrameTimeVector (mean)"
    origin = floats_tag(ds, "DetectorActiveOrigin", name)
    if origin and len(origin) == 2 and found.get("pixel_spacing_mm") is not None:
        physical = floats_tag(ds, "PhysicalDetectorSize", name)
        active = floats_tag(ds, "DetectorActiveDimensions", name)
        spacing = _normalise("pixel_spacing_mm", found["pixel_spacing_mm"], f"{sources['pixel_spacing_mm']} in {name}")
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
        "bits_stored": int_tag(ds, "BitsStored", path.name, 0),
        "transfer_syntax": str(ds.file_meta.get("TransferSyntaxUID", "")) if hasattr(ds, "file_meta") else "",
    }
    for key in ("PatientID", "StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "SOPClassUID", "Modality", "SeriesDescription"):
        if ds.get(key) not in (None, ""):
            meta[key] = str(ds.get(key))
    return meta


def _declared_photometric(ds: pydicom.Dataset) -> str:
    return str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip()


def _frames(ds: pydicom.Dataset, name: str) -> tuple[np.ndarray, dict]:
    return decode_frames(ds, name, lambda shape: check_frames_shape(shape, name))


def _read_dicom_file(path: Path, overrides: dict, photometric: str | None) -> DSARun:
    ds = read_dataset(path)
    frames, notes = _frames(ds, path.name)
    found, sources, geo_notes = _dicom_geometry(ds, frames.shape[1], frames.shape[2], path.name)
    meta = _dicom_metadata(ds, path, [path])
    meta.update(notes, **geo_notes)
    declared = _declared_photometric(ds)
    plan = read_mask_subtraction(ds, len(frames), path.name)
    if plan is not None:  # a native run: subtracted here, onto an 8-bit display's scale, MONOCHROME2
        frames = subtract_mask(frames, plan)
        meta.update(subtraction=plan.describe(), bits_stored=8)
        declared = "MONOCHROME2"
    _photometric(declared, photometric, frames, path.name, meta)
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


def _dicom_headers(folder: Path) -> list[tuple[Path, pydicom.Dataset]]:
    """(file, header) of every DICOM file of ``folder``; files not meant to be DICOM are skipped, damaged
    DICOM files refused (a frame dropped silently would change the run)."""
    headers = []
    for f in folder_files(folder, "DSA run"):
        try:
            headers.append((f, read_dataset(f, stop_before_pixels=True)))
        except InputError as exc:
            if "is not a DICOM file" not in str(exc) or looks_like_dicom(f):
                raise
    return headers


def _read_dicom_folder(folder: Path, overrides: dict, photometric: str | None) -> DSARun:
    headers = [(f, ds) for f, ds in _dicom_headers(folder) if "Rows" in ds]
    if not headers:
        raise InputError(f"{folder} holds no DICOM images: point to the folder of the run's frames or to its file")
    multi = [f for f, ds in headers if int_tag(ds, "NumberOfFrames", f.name, 1) > 1]
    if len(headers) == 1 or multi:
        if len(headers) == 1:
            return _read_dicom_file(headers[0][0], overrides, photometric)
        raise InputError(f"{folder} mixes {len(multi)} multi-frame file(s) with other images: pass the run's file itself")
    series = {str(ds.get("SeriesInstanceUID", "")) for _, ds in headers}
    if len(series) > 1:
        raise InputError(f"{folder} holds {len(series)} series: put one run's frames in a folder of their own")
    check_frames_shape((len(headers), int_tag(headers[0][1], "Rows", headers[0][0].name), int_tag(headers[0][1], "Columns", headers[0][0].name)),
                       folder.name)
    headers.sort(key=lambda fd: (int_tag(fd[1], "InstanceNumber", fd[0].name, 0), _dicom_time_s(fd[1]) or 0.0, fd[0].name))
    first = headers[0][1]
    for f, ds in headers[1:]:
        for key in ("PositionerPrimaryAngle", "PositionerSecondaryAngle"):
            a, b = float_tag(first, key, headers[0][0].name), float_tag(ds, key, f.name)
            if a is not None and b is not None and abs(a - b) > ANGLE_TOLERANCE_DEG:
                raise InputError(f"{f.name} has {key} {b} but the first frame {a}: the folder is not one fixed-angle run")
    size = (int_tag(first, "Rows", headers[0][0].name), int_tag(first, "Columns", headers[0][0].name))
    frames = np.empty((len(headers),) + size, dtype=np.float32)  # bounded by check_frames_shape above
    integrity = set()
    for k, (f, _) in enumerate(headers):
        frame, frame_notes = _frames(read_dataset(f), f.name)
        if frame.shape != (1,) + size:
            raise InputError(f"{folder} holds frames of different sizes ({f.name}: {frame.shape[1:]}, {headers[0][0].name}: "
                             f"{size}): the folder is not one run")
        frames[k] = frame[0]
        integrity.add(frame_notes["pixel_integrity"])
    found, sources, notes = _dicom_geometry(first, frames.shape[1], frames.shape[2], headers[0][0].name)
    if "frame_time_ms" not in sources:
        times = [t for t in (_dicom_time_s(ds) for _, ds in headers) if t is not None]
        if len(times) == len(headers) > 1 and np.all(np.diff(times) > 0):
            found["frame_time_ms"] = float(np.median(np.diff(times)) * 1000.0)
            sources["frame_time_ms"] = "AcquisitionTime/ContentTime differences"
    meta = _dicom_metadata(first, folder, [f for f, _ in headers])
    meta.update(notes, pixel_integrity="; ".join(sorted(integrity)))
    _photometric(_declared_photometric(first), photometric, frames, folder.name, meta)
    return _assemble(frames, found, sources, overrides, folder.name, lambda k: GEOMETRY_SOURCES[k], meta)


# ---------------------------------------------------------------- NIfTI + sidecar


def _frames_shape(declared: tuple[int, ...], path: Path) -> tuple[int, int, int]:
    """(T, H, W) of a header's grid (x = columns, y = rows, then frames; a 4D grid with z = 1)."""
    sizes = list(declared)
    if len(sizes) == 4 and sizes[2] == 1:
        sizes = sizes[:2] + sizes[3:]
    if len(sizes) == 2:
        sizes.append(1)
    if len(sizes) != 3:
        raise InputError(f"{path.name} has size {tuple(declared)}: a DSA run is 2D+time (columns, rows, frames)")
    return sizes[2], sizes[1], sizes[0]


def _read_sidecar(side: Path) -> dict[str, Any]:
    remedy = f"fix the sidecar (keys {', '.join(SIDECAR_KEYS)}) or delete it and pass the geometry as overrides"
    found = read_json(side, remedy)
    if not isinstance(found, dict):
        raise InputError(f"{side.name} must hold a JSON object with keys {', '.join(SIDECAR_KEYS)}")
    unknown = sorted(set(found) - set(SIDECAR_KEYS))
    if unknown:
        raise InputError(f"{side.name} has unknown key(s) {unknown}; valid keys: {', '.join(SIDECAR_KEYS)}")
    return found


def _read_image_with_sidecar(path: Path, overrides: dict, photometric: str | None) -> DSARun:
    declared = check_image_file(path, L.DSA_MAX_PIXELS)
    shape = _frames_shape(declared.shape, path)
    check_frames_shape(shape, path.name)
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else "no detail"
        raise InputError(f"cannot read {path} as an image ({detail}): check the file") from None
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"{path.name} has {image.GetNumberOfComponentsPerPixel()} components per pixel: store greyscale frames")
    array = sitk.GetArrayFromImage(image).astype(np.float32)
    if array.size != int(np.prod(shape)):
        raise InputError(f"{path.name}: SimpleITK read {array.size} pixels but the header declares {shape}: the header is damaged")
    array = array.reshape(shape)
    side = sidecar_path(path)
    found = _read_sidecar(side) if side.exists() else {}  # a special file named like a sidecar is refused by read_json
    declared_pi = found.pop("photometric_interpretation", "MONOCHROME2")
    if declared_pi not in PHOTOMETRIC:
        raise InputError(f"photometric_interpretation in {side.name} must be MONOCHROME1 or MONOCHROME2, got {declared_pi!r}")
    sources = {k: side.name for k in found}
    files = declared.files + ([side] if side.exists() else [])
    meta = {
        "source_path": str(path.resolve()),
        "source_files": len(files),
        "sha256": file_sha256(files),
        "pixel_integrity": "; ".join(declared.checks),
    }
    _photometric(declared_pi, photometric, array, path.name, meta)

    def where(key: str) -> str:
        return f"'{key}' (sidecar {side.name})"

    return _assemble(array, found, sources, overrides, path.name, where, meta)


def read_dsa(path: str | Path, *, photometric_interpretation: str | None = None, **overrides: Any) -> DSARun:
    """Read a DSA run from a DICOM file (XA multi-frame or single frame; uncompressed,
    JPEG Baseline/Lossless, JPEG-LS, JPEG 2000 or RLE), a folder of single-frame DICOMs (sorted
    by InstanceNumber then acquisition time) or a NIfTI/NRRD/MHA 2D+time image with a
    ``<name>.json`` geometry sidecar. Keyword overrides (``primary_deg``, ``secondary_deg``,
    ``sid_mm``, ``sod_mm``, ``pixel_spacing_mm`` (row, col) or one value,
    ``principal_offset_mm`` (x0, y0), ``frame_time_ms``) replace file values; ``None``
    leaves the file value. ``photometric_interpretation`` (MONOCHROME1/2) replaces the
    file's. Anything missing, damaged or implausible raises :class:`InputError` naming the
    tag/key and the remedy.
    """
    path = Path(path)
    if input_kind(path, "DSA run") == "folder":
        return _read_dicom_folder(path, overrides, photometric_interpretation)
    if image_extension(path) in NIFTI_EXTENSIONS:
        return _read_image_with_sidecar(path, overrides, photometric_interpretation)
    return _read_dicom_file(path, overrides, photometric_interpretation)
