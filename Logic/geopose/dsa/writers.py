"""Writers for DSA runs: DICOM XA multi-frame (uncompressed) and NIfTI + JSON sidecar."""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk
from PIL import Image, ImageDraw
from pydicom.dataset import FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, XRayAngiographicImageStorage, generate_uid

from .readers import sidecar_path
from ..errors import InputError
from .run import DSARun
from .subtraction import MaskSubtraction, mask_subtraction_item

__all__ = ["write_dsa_dicom", "write_dsa_nifti", "quantize_frames"]

#: Margin (px) of burnt-in text from the top-left corner.
BURN_IN_MARGIN_PX = 4
#: ``Dataset.save_as`` keyword for a standard file (preamble + file meta): pydicom 3's
#: ``enforce_file_format=True`` is ``write_like_original=False`` in pydicom 2.4 (bundled
#: with Slicer 5.8 and 5.10).
_STANDARD_FILE = {"enforce_file_format": True} if int(pydicom.__version__.split(".")[0]) >= 3 else {"write_like_original": False}


def quantize_frames(frames: np.ndarray, bits: int) -> tuple[np.ndarray, float, float]:
    """Stored integers and the (slope, intercept) with ``value ~= stored * slope + intercept``.

    Integer-valued frames inside ``[0, 2**bits - 1]`` are stored exactly (slope 1,
    intercept 0); anything else is mapped linearly onto the full range (max error
    ``slope / 2``).
    """
    top = 2**bits - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    lo, hi = float(frames.min()), float(frames.max())
    if lo >= 0 and hi <= top and np.array_equal(frames, np.round(frames)):
        return frames.astype(dtype), 1.0, 0.0
    slope = (hi - lo) / top if hi > lo else 1.0
    stored = np.clip(np.round((frames - lo) / slope), 0, top).astype(dtype)
    return stored, slope, lo


def _burn_in(stored: np.ndarray, text: str, value: int) -> None:
    """Draw ``text`` into every frame (in place), top-left, with pixel value ``value``."""
    h, w = stored.shape[1:]
    layer = Image.new("L", (w, h), 0)
    ImageDraw.Draw(layer).text((BURN_IN_MARGIN_PX, BURN_IN_MARGIN_PX), text, fill=255)
    ink = np.asarray(layer) > 127
    stored[:, ink] = value


def write_dsa_dicom(
    run: DSARun,
    path: str | Path,
    *,
    patient_name: str = "GeoPose^Phantom",
    patient_id: str = "GEOPOSE-PHANTOM",
    series_description: str = "GeoPose DSA",
    burn_in_text: str | None = None,
    bits: int = 16,
    study_instance_uid: str | None = None,
    mask_subtraction: MaskSubtraction | None = None,
) -> Path:
    """Write ``run`` as an uncompressed DICOM XA multi-frame (X-Ray Angiographic Image Storage).

    Identity: ``patient_id``, and ``study_instance_uid`` (else the run's metadata's, else a new one): give the
    runs of one biplane acquisition one study.

    Pixel data: ``bits`` 8 or 16, unsigned, MONOCHROME2 when the run is MONOCHROME2
    (MONOCHROME1 runs keep MONOCHROME1); non-integer values are quantised with
    :func:`quantize_frames` and the mapping is stored as RescaleSlope/Intercept.
    Geometry: PositionerPrimaryAngle/SecondaryAngle, DistanceSourceToDetector,
    DistanceSourceToPatient, ImagerPixelSpacing (row, col), FrameTime + FrameIncrementPointer,
    and, for a non-zero principal offset, DetectorActiveOrigin/DetectorActiveDimensions/
    PhysicalDetectorSize encoding it as the reader decodes it. ``burn_in_text`` is drawn
    into every frame (BurnedInAnnotation YES). ``mask_subtraction``: ``run`` is native (X-ray intensities, LIN) and
    is written as an angiography system archives it, with the Mask Subtraction Sequence that subtracts it
    (Recommended Viewing Mode SUB).
    """
    if bits not in (8, 16):
        raise InputError(f"bits must be 8 or 16, got {bits}")
    path = Path(path)
    stored, slope, intercept = quantize_frames(run.frames, bits)
    if burn_in_text:
        _burn_in(stored, burn_in_text, int(stored.max()) if stored.max() > 0 else 2**bits - 1)
    t, h, w = stored.shape
    now = _dt.datetime.now()
    sop_uid = generate_uid()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = XRayAngiographicImageStorage
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = pydicom.Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = XRayAngiographicImageStorage, sop_uid
    ds.Modality = "XA"
    ds.ImageType = ["ORIGINAL" if mask_subtraction else "DERIVED", "PRIMARY", "SINGLE PLANE", "SINGLE A"]
    ds.PatientName, ds.PatientID = patient_name, patient_id
    ds.StudyInstanceUID = study_instance_uid or run.metadata.get("StudyInstanceUID") or generate_uid()
    ds.SeriesInstanceUID = generate_uid()
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.SeriesDescription = series_description
    ds.SeriesNumber, ds.InstanceNumber = 1, 1
    ds.BurnedInAnnotation = "YES" if burn_in_text else "NO"
    a = run.angles
    ds.PositionerPrimaryAngle = f"{a.primary_deg:.6g}"
    ds.PositionerSecondaryAngle = f"{a.secondary_deg:.6g}"
    ds.DistanceSourceToDetector = f"{a.sid_mm:.6g}"
    ds.DistanceSourceToPatient = f"{a.sod_mm:.6g}"
    dy, dx = run.detector.spacing_mm
    ds.ImagerPixelSpacing = [f"{dy:.10g}", f"{dx:.10g}"]
    x0, y0 = run.detector.principal_offset_mm
    if x0 or y0:
        # image centre offset (down, right) from the detector centre is (-y0, -x0)
        ds.PhysicalDetectorSize = [h * dy + 2 * abs(y0), w * dx + 2 * abs(x0)]
        ds.DetectorActiveDimensions = [f"{h * dy:.10g}", f"{w * dx:.10g}"]
        ds.DetectorActiveOrigin = [f"{abs(y0) - y0:.10g}", f"{abs(x0) - x0:.10g}"]
    ds.FrameTime = f"{run.frame_time_ms:.6g}" if run.frame_time_ms else "0"
    ds.NumberOfFrames = t
    ds.FrameIncrementPointer = pydicom.tag.Tag("FrameTime")
    ds.Rows, ds.Columns = h, w
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME1" if run.photometric_interpretation == "MONOCHROME1" else "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = bits
    ds.HighBit = bits - 1
    ds.PixelRepresentation = 0
    ds.PixelIntensityRelationship = "LIN"
    if mask_subtraction is not None:
        ds.PixelIntensityRelationship = mask_subtraction.relationship
        ds.MaskSubtractionSequence = [mask_subtraction_item(mask_subtraction)]
        ds.RecommendedViewingMode = "SUB"
    if (slope, intercept) != (1.0, 0.0):
        ds.RescaleSlope, ds.RescaleIntercept = f"{slope:.10g}", f"{intercept:.10g}"
        ds.RescaleType = "US"
    ds.PixelData = stored.tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(path, **_STANDARD_FILE)
    return path


def write_dsa_nifti(run: DSARun, path: str | Path) -> Path:
    """Write frames as a 2D+time NIfTI/NRRD/MHA (size columns x rows x frames, float32;
    spacing col mm, row mm, frame ms or 1) and the geometry as ``<name>.json`` beside it."""
    path = Path(path)
    image = sitk.GetImageFromArray(np.ascontiguousarray(run.frames))
    dy, dx = run.detector.spacing_mm
    image.SetSpacing((dx, dy, run.frame_time_ms or 1.0))
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(image, str(path))
    a = run.angles
    sidecar = {
        "primary_deg": a.primary_deg,
        "secondary_deg": a.secondary_deg,
        "sid_mm": a.sid_mm,
        "sod_mm": a.sod_mm,
        "pixel_spacing_mm": [dy, dx],
        "principal_offset_mm": list(run.detector.principal_offset_mm),
        "photometric_interpretation": run.photometric_interpretation,
    }
    if run.frame_time_ms:
        sidecar["frame_time_ms"] = run.frame_time_ms
    sidecar_path(path).write_text(json.dumps(sidecar, indent=2) + "\n")
    return path
