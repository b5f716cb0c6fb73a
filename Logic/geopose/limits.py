"""Plausibility bounds of every input and option, named once.

Each bound is a closed interval ``(lo, hi)`` in the unit its name carries. Readers,
the options type and the Slicer panel check against these; :func:`check_range`
raises :class:`~geopose.errors.InputError` with the name, the value, the bound and
the remedy.
"""

from __future__ import annotations

import math
from typing import Final

from .errors import InputError

__all__ = [
    "REFINE_STEPS", "ITERATIONS", "TTO_PX", "RENDER_PX", "VOXEL_PER_PIXEL", "WORK_SPACING_MM", "CLIP_PERCENTILE",
    "CTA_VOXEL_SIZE_MM", "CTA_EXTENT_MM", "CTA_VOXELS_PER_AXIS", "CTA_MAX_VOXELS", "CTA_RESAMPLE_MAX_GROWTH", "CTA_PLAUSIBLE_HU",
    "CTA_MAX_IMPLAUSIBLE_SHARE", "CTA_AIR_MAX_HU", "CTA_MIN_SPAN_HU", "HU_OFFSET",
    "SLICE_GAP_TOLERANCE", "SLICE_GAP_TOLERANCE_MM", "SLICE_ORIENTATION_TOLERANCE",
    "DSA_MATRIX_PX", "DSA_FRAMES", "DSA_MAX_PIXELS", "ANGLE_INPUT_DEG", "PRIMARY_DEG", "SECONDARY_DEG",
    "SID_MM", "SOD_MM", "PIXEL_SPACING_MM", "PRINCIPAL_OFFSET_MM", "FRAME_TIME_MS",
    "MAX_DICOM_FILE_BYTES", "MAX_IMAGE_FILE_BYTES", "MAX_JSON_BYTES", "MAX_JSON_DEPTH",
    "MAX_CHECKPOINT_STORAGE_BYTES", "MAX_CHECKPOINT_TOTAL_BYTES", "MAX_CHECKPOINT_TENSOR_ELEMENTS",
    "check_range", "check_int", "wrap_angle_deg",
]

# ---------------------------------------------------------------- options
#: Greedy refinement proposals per view.
REFINE_STEPS: Final = (0, 20)
#: Test-time optimisation steps.
ITERATIONS: Final = (0, 2000)
#: TTO image size (pixels along the detector's longer side).
TTO_PX: Final = (32, 1024)
#: Network-input render size (pixels along a side) before resizing to the model detector.
RENDER_PX: Final = (32, 512)
#: Voxels per pixel footprint of the coarsest CTA level a render may sample.
VOXEL_PER_PIXEL: Final = (0.5, 8.0)
#: Voxel size (mm) of the working copy of the CTA the renderers sample.
WORK_SPACING_MM: Final = (0.25, 4.0)
#: Intensity clip percentiles of a MAP.
CLIP_PERCENTILE: Final = (0.0, 100.0)

# ---------------------------------------------------------------- CT(A) volumes
#: Voxel size (mm) along each axis of a CT(A) of a head.
CTA_VOXEL_SIZE_MM: Final = (0.05, 10.0)
#: Edge-to-edge extent (mm) along each axis: a slab of a head up to a whole-body scan.
CTA_EXTENT_MM: Final = (20.0, 2000.0)
#: Voxels along each axis.
CTA_VOXELS_PER_AXIS: Final = (8, 4096)
#: Voxels in all (2**30: 4 GiB as float32), checked on the header before any voxel is read; a DICOM series is
#: decoded slice by slice into one float32 array of this size at most (and resampled into another, see below).
CTA_MAX_VOXELS: Final = 2**30
#: A series resampled onto a regular grid (gantry tilt, uneven gaps) may hold at most this many times the
#: acquired voxels, checked before the grid is allocated (a tilt of 30 deg over a 200 mm stack of 0.5 mm
#: pixels grows a slice by about 1.4 times, uneven gaps add slices up to the ratio of the gaps).
CTA_RESAMPLE_MAX_GROWTH: Final = 4
#: HU a CT voxel can hold (air with noise .. dense bone and contrast); padding is not counted.
CTA_PLAUSIBLE_HU: Final = (-1100.0, 4000.0)
#: Largest share of voxels (0..1) outside :data:`CTA_PLAUSIBLE_HU` in a CT read right (metal streaks, noise).
CTA_MAX_IMPLAUSIBLE_SHARE: Final = 0.05
#: A CT of a head in HU contains air: its minimum lies below this value (HU).
CTA_AIR_MAX_HU: Final = -200.0
#: A value span (HU) this small suggests a normalised (e.g. 0..1) image, not HU.
CTA_MIN_SPAN_HU: Final = 2.0
#: ``hu_offset`` (HU) added to a CTA's stored values.
HU_OFFSET: Final = (-4096.0, 4096.0)
#: Slice gaps of a DICOM series count as even when within this fraction of their median...
SLICE_GAP_TOLERANCE: Final = 0.02
#: ...or within this many mm (whichever is larger).
SLICE_GAP_TOLERANCE_MM: Final = 0.01
#: Largest difference between the slices' direction cosines (ImageOrientationPatient) of one series.
SLICE_ORIENTATION_TOLERANCE: Final = 1e-3

# ---------------------------------------------------------------- DSA runs
#: Pixels along each side of a DSA frame.
DSA_MATRIX_PX: Final = (32, 4096)
#: Frames of one run.
DSA_FRAMES: Final = (1, 10000)
#: Pixels of a run in all (frames x rows x columns; 2**30: 4 GiB as float32), checked on the header; the frames
#: are decoded one at a time into one float32 array of that size (no integer copy of the whole run).
DSA_MAX_PIXELS: Final = 2**30
#: Positioner angles as read (deg), before they are wrapped to (-180, 180].
ANGLE_INPUT_DEG: Final = (-360.0, 360.0)
#: PositionerPrimaryAngle after wrapping (deg): any LAO/RAO rotation.
PRIMARY_DEG: Final = (-180.0, 180.0)
#: PositionerSecondaryAngle after wrapping (deg): cranial/caudal tilt of a C-arm.
SECONDARY_DEG: Final = (-90.0, 90.0)
#: Source-to-detector distance (mm) of an angiography C-arm.
SID_MM: Final = (500.0, 2000.0)
#: Source-to-isocentre distance (mm); it must also be shorter than the SID.
SOD_MM: Final = (200.0, 1500.0)
#: Detector-plane pixel spacing (mm).
PIXEL_SPACING_MM: Final = (0.02, 5.0)
#: Principal point offset (mm) of the image centre from the central ray.
PRINCIPAL_OFFSET_MM: Final = (-300.0, 300.0)
#: Time between frames (ms).
FRAME_TIME_MS: Final = (0.01, 100000.0)

# ---------------------------------------------------------------- files
#: Largest DICOM file read (bytes); the file is read whole, so no element length can allocate more.
MAX_DICOM_FILE_BYTES: Final = 2**31
#: Largest NIfTI/NRRD/MetaImage file (bytes, also the decompressed size of a .nii.gz).
MAX_IMAGE_FILE_BYTES: Final = 2**33
#: Largest JSON sidecar or model manifest (bytes).
MAX_JSON_BYTES: Final = 2**24
#: Deepest nesting of JSON objects/arrays read (a sidecar is flat; a manifest a few levels).
MAX_JSON_DEPTH: Final = 32
#: Largest tensor storage of an imported checkpoint (bytes, as declared in its zip directory).
MAX_CHECKPOINT_STORAGE_BYTES: Final = 2**30
#: Largest sum of all storages of an imported checkpoint (bytes).
MAX_CHECKPOINT_TOTAL_BYTES: Final = 2**32
#: Largest tensor (elements) rebuilt from a checkpoint's storage.
MAX_CHECKPOINT_TENSOR_ELEMENTS: Final = 2**28


def check_range(name: str, value: float, bound: tuple[float, float], remedy: str = "") -> float:
    """``value`` as a float if finite and within ``bound``, else an :class:`InputError`."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}{'; ' + remedy if remedy else ''}") from None
    lo, hi = bound
    if not math.isfinite(v) or not lo <= v <= hi:
        raise InputError(f"{name} = {value!r} is outside the plausible range {lo:g}..{hi:g}{'; ' + remedy if remedy else ''}")
    return v


def check_int(name: str, value: object, bound: tuple[int, int], remedy: str = "") -> int:
    """``value`` if it is a whole number (not a bool, not a fraction) within ``bound``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not value.is_integer()):
        raise InputError(f"{name} must be a whole number, got {value!r}{'; ' + remedy if remedy else ''}")
    check_range(name, value, bound, remedy)
    return int(value)


def wrap_angle_deg(name: str, value: float, bound: tuple[float, float], remedy: str = "") -> float:
    """``value`` (deg, within :data:`ANGLE_INPUT_DEG`) wrapped to (-180, 180], then checked against ``bound``
    (e.g. 346.6 -> -13.4)."""
    v = check_range(name, value, ANGLE_INPUT_DEG, remedy)
    wrapped = v - 360.0 * math.ceil((v - 180.0) / 360.0)
    return check_range(name, wrapped, bound, remedy)
