"""The DSA run data contract and the geometry keys every reader shares.

A :class:`DSARun` holds the frames as stored (modality LUT applied, never inverted)
with the C-arm geometry that the registration needs. Geometry keys (sidecar JSON,
keyword overrides and CLI options use the same names):

=====================  ===============================  ======================================
key                    DICOM source                     meaning
=====================  ===============================  ======================================
``primary_deg``        PositionerPrimaryAngle           LAO positive (deg); gives the view role
``secondary_deg``      PositionerSecondaryAngle         cranial positive (deg)
``sid_mm``             DistanceSourceToDetector         source-to-detector distance = SDD (mm)
``sod_mm``             DistanceSourceToPatient          source-to-isocentre distance (mm)
``pixel_spacing_mm``   ImagerPixelSpacing / PixelSpacing  detector-plane [row, col] spacing (mm)
``principal_offset_mm``  DetectorActiveOrigin (see readers)  camera (x0, y0) of the image centre (mm)
``frame_time_ms``      FrameTime / FrameTimeVector      time between frames (ms), optional
=====================  ===============================  ======================================
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from .. import contract as C
from .. import limits as L
from ..errors import InputError
from ..geometry.detector import CArmAngles, Detector, view_from_primary_angle

__all__ = [
    "DSARun",
    "GEOMETRY_KEYS",
    "REQUIRED_GEOMETRY_KEYS",
    "GEOMETRY_SOURCES",
    "PHOTOMETRIC",
    "check_frames_shape",
    "check_geometry",
    "cli_hint",
    "cli_option",
    "PA_ROLE",
    "LAT_ROLE",
]

PA_ROLE = "PA"
LAT_ROLE = "LAT"

#: Photometric interpretations of a greyscale run.
PHOTOMETRIC = ("MONOCHROME1", "MONOCHROME2")

REQUIRED_GEOMETRY_KEYS = ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm")
GEOMETRY_KEYS = REQUIRED_GEOMETRY_KEYS + ("principal_offset_mm", "frame_time_ms")

#: Where each key comes from in a DICOM file (used in error messages).
GEOMETRY_SOURCES = {
    "primary_deg": "PositionerPrimaryAngle (0018,1510)",
    "secondary_deg": "PositionerSecondaryAngle (0018,1511)",
    "sid_mm": "DistanceSourceToDetector (0018,1110)",
    "sod_mm": "DistanceSourceToPatient (0018,1111)",
    "pixel_spacing_mm": "ImagerPixelSpacing (0018,1164), PixelSpacing (0028,0030) or FieldOfViewDimensions (0018,1149)",
    "principal_offset_mm": "DetectorActiveOrigin (0018,7028)",
    "frame_time_ms": "FrameTime (0018,1063)",
}


def cli_option(key: str) -> str:
    """The command-line option stem of a geometry key, e.g. ``sid_mm`` -> ``--sid-mm``."""
    return "--" + key.replace("_", "-")


def cli_hint(key: str) -> str:
    """The ``geopose register`` options that set ``key`` for either view, e.g. ``--pa-sid-mm / --lat-sid-mm``."""
    stem = cli_option(key)[2:]
    return f"--pa-{stem} / --lat-{stem}"


#: Plausibility bound of each scalar geometry key (the pixel spacing and principal offset apply per component).
_BOUNDS: dict[str, tuple[float, float]] = {
    "sid_mm": L.SID_MM,
    "sod_mm": L.SOD_MM,
    "pixel_spacing_mm": L.PIXEL_SPACING_MM,
    "principal_offset_mm": L.PRINCIPAL_OFFSET_MM,
    "frame_time_ms": L.FRAME_TIME_MS,
}
_ANGLE_BOUNDS = {"primary_deg": L.PRIMARY_DEG, "secondary_deg": L.SECONDARY_DEG}


def _default_where(key: str) -> str:
    return f"'{key}'"


def check_frames_shape(shape: tuple[int, ...], name: str) -> None:
    """Refuse a run of ``(T, H, W)`` frames outside :data:`~geopose.limits.DSA_MATRIX_PX`,
    :data:`~geopose.limits.DSA_FRAMES` or :data:`~geopose.limits.DSA_MAX_PIXELS` (called on the
    header's numbers before any pixel is decoded, and on every :class:`DSARun`)."""
    t, h, w = (int(v) for v in shape)
    lo, hi = L.DSA_MATRIX_PX
    if not (lo <= h <= hi and lo <= w <= hi):
        raise InputError(f"{name} has {h} x {w} pixels per frame: a DSA frame has {lo}..{hi} pixels along each side; "
                         "export the run at its acquired resolution")
    if not L.DSA_FRAMES[0] <= t <= L.DSA_FRAMES[1]:
        raise InputError(f"{name} declares {t} frames: a run has {L.DSA_FRAMES[0]}..{L.DSA_FRAMES[1]}; check NumberOfFrames "
                         "or the image's time axis")
    if t * h * w > L.DSA_MAX_PIXELS:
        raise InputError(f"{name} declares {t} x {h} x {w} pixels, more than the {L.DSA_MAX_PIXELS} a run may hold: "
                         "export the arterial phase only or fewer frames")


def check_geometry(
    values: dict[str, Any], name: str, where: Callable[[str], str] = _default_where
) -> dict[str, Any]:
    """Geometry values (``GEOMETRY_KEYS`` names; floats, pairs for the spacing and offset)
    within the plausibility bounds of :mod:`geopose.limits`, angles wrapped to (-180, 180]
    (346.6 deg becomes -13.4 deg), SOD shorter than SID. Returns the checked values; raises
    :class:`InputError` naming the key, where it came from (``where(key)``) and the remedy."""
    out = dict(values)

    def remedy(key: str) -> str:
        return f"check {where(key)} in {name} or pass {key}=... (CLI: {cli_hint(key)})"

    for key, bound in _ANGLE_BOUNDS.items():
        if key in out:
            out[key] = L.wrap_angle_deg(key, out[key], bound, remedy(key))
    for key, bound in _BOUNDS.items():
        if key not in out or out[key] is None:
            continue
        if isinstance(out[key], tuple):
            out[key] = tuple(L.check_range(key, v, bound, remedy(key)) for v in out[key])
        else:
            out[key] = L.check_range(key, out[key], bound, remedy(key))
    if "sid_mm" in out and "sod_mm" in out and not out["sod_mm"] < out["sid_mm"]:
        raise InputError(
            f"source-to-isocentre distance {out['sod_mm']:g} mm is not shorter than the source-to-detector distance "
            f"{out['sid_mm']:g} mm in {name}: check sod_mm / sid_mm (CLI: {cli_hint('sod_mm')}, {cli_hint('sid_mm')})"
        )
    return out


@dataclass
class DSARun:
    """One DSA acquisition (a single C-arm view).

    ``frames``: ``(T, H, W)`` float32 stored pixel values (DICOM modality LUT applied,
    no inversion, no VOI LUT). ``detector``: rows = H, cols = W, ``spacing_mm`` =
    (row, col) detector-plane spacing, ``sdd_mm`` = SID. ``angles``: positioner angles
    (deg), SID and SOD (mm). ``metadata``: source path, SHA-256, UIDs,
    ``photometric_interpretation`` and where every geometry value came from.
    """

    frames: np.ndarray
    detector: Detector
    angles: CArmAngles
    frame_time_ms: float | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        name = str(self.metadata.get("source_path", "the DSA run"))
        self.frames = np.asarray(self.frames, dtype=np.float32)
        if self.frames.ndim == 2:
            self.frames = self.frames[None]
        if self.frames.ndim != 3 or min(self.frames.shape) < 1:
            raise InputError(f"DSA frames must be (T, H, W), got shape {self.frames.shape}")
        check_frames_shape(self.frames.shape, name)
        if self.frames.shape[1:] != self.detector.shape:
            raise InputError(f"frames are {self.frames.shape[1:]} pixels but the detector is {self.detector.shape}")
        if not np.all(np.isfinite(self.frames)):
            raise InputError(f"{name}: DSA frames contain NaN or infinite values: fix the export")
        if abs(self.angles.sid_mm - self.detector.sdd_mm) > 1e-6:
            raise InputError(f"SID {self.angles.sid_mm} mm differs from the detector SDD {self.detector.sdd_mm} mm")
        a, d = self.angles, self.detector
        checked = check_geometry(
            {"primary_deg": a.primary_deg, "secondary_deg": a.secondary_deg, "sid_mm": a.sid_mm, "sod_mm": a.sod_mm,
             "pixel_spacing_mm": tuple(d.spacing_mm), "principal_offset_mm": tuple(d.principal_offset_mm),
             "frame_time_ms": self.frame_time_ms},
            name,
        )
        if (checked["primary_deg"], checked["secondary_deg"]) != (a.primary_deg, a.secondary_deg):
            self.angles = replace(a, primary_deg=checked["primary_deg"], secondary_deg=checked["secondary_deg"])

    @property
    def view_label(self) -> int:
        """View class from the primary angle (0 LAT-, 1 PA, 2 LAT+), see ``view_from_primary_angle``."""
        return view_from_primary_angle(self.angles.primary_deg)

    @property
    def view_role(self) -> str:
        """``"PA"`` or ``"LAT"``: the only view information the pipeline takes from metadata."""
        return PA_ROLE if self.view_label == C.VIEW_PA else LAT_ROLE

    @property
    def photometric_interpretation(self) -> str:
        return str(self.metadata.get("photometric_interpretation", "MONOCHROME2"))

    def attenuation(self, invert: bool | None = None) -> np.ndarray:
        """Frames as an attenuation-like image (contrast and bone bright, like a DRR).

        Angiography displays absorbing structures dark (contrast-filled vessels black on
        grey); with MONOCHROME2 that means low stored values, so the frames are inverted
        (``max - frames``). MONOCHROME1 shows low values white, i.e. absorbers already have
        high stored values, so the frames are kept. ``invert`` overrides this choice for
        data stored the other way round. Returns a new float32 ``(T, H, W)`` array.
        """
        if invert is None:
            invert = self.photometric_interpretation != "MONOCHROME1"
        return (self.frames.max() - self.frames) if invert else self.frames.copy()

    @classmethod
    def from_attenuation(
        cls,
        attenuation: np.ndarray,
        detector: Detector,
        angles: CArmAngles,
        frame_time_ms: float | None = None,
        metadata: dict | None = None,
    ) -> "DSARun":
        """Build a MONOCHROME2 run whose stored frames show absorbers dark (``max - attenuation``),
        e.g. from DRR line integrals; :meth:`attenuation` gives the input back minus its minimum."""
        att = np.asarray(attenuation, dtype=np.float32)
        meta = dict(metadata or {})
        meta["photometric_interpretation"] = "MONOCHROME2"
        return cls(att.max() - att, detector, angles, frame_time_ms, meta)
