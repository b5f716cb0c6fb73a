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

from dataclasses import dataclass, field

import numpy as np

from .. import contract as C
from ..geometry.detector import CArmAngles, Detector, view_from_primary_angle

__all__ = [
    "DSAInputError",
    "DSARun",
    "GEOMETRY_KEYS",
    "REQUIRED_GEOMETRY_KEYS",
    "GEOMETRY_SOURCES",
    "cli_option",
    "PA_ROLE",
    "LAT_ROLE",
]

PA_ROLE = "PA"
LAT_ROLE = "LAT"

REQUIRED_GEOMETRY_KEYS = ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm")
GEOMETRY_KEYS = REQUIRED_GEOMETRY_KEYS + ("principal_offset_mm", "frame_time_ms")

#: Where each key comes from in a DICOM file (used in error messages).
GEOMETRY_SOURCES = {
    "primary_deg": "PositionerPrimaryAngle (0018,1510)",
    "secondary_deg": "PositionerSecondaryAngle (0018,1511)",
    "sid_mm": "DistanceSourceToDetector (0018,1110)",
    "sod_mm": "DistanceSourceToPatient (0018,1111)",
    "pixel_spacing_mm": "ImagerPixelSpacing (0018,1164) or PixelSpacing (0028,0030)",
    "principal_offset_mm": "DetectorActiveOrigin (0018,7028)",
    "frame_time_ms": "FrameTime (0018,1063)",
}


def cli_option(key: str) -> str:
    """The command-line option of a geometry key, e.g. ``sid_mm`` -> ``--sid-mm``."""
    return "--" + key.replace("_", "-")


class DSAInputError(ValueError):
    """A DSA input that cannot be used; the message names the problem and the remedy."""


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
        self.frames = np.asarray(self.frames, dtype=np.float32)
        if self.frames.ndim == 2:
            self.frames = self.frames[None]
        if self.frames.ndim != 3 or min(self.frames.shape) < 1:
            raise DSAInputError(f"DSA frames must be (T, H, W), got shape {self.frames.shape}")
        if self.frames.shape[1:] != self.detector.shape:
            raise DSAInputError(f"frames are {self.frames.shape[1:]} pixels but the detector is {self.detector.shape}")
        if not np.all(np.isfinite(self.frames)):
            raise DSAInputError("DSA frames contain NaN or infinite values: fix the export")
        if abs(self.angles.sid_mm - self.detector.sdd_mm) > 1e-6:
            raise DSAInputError(f"SID {self.angles.sid_mm} mm differs from the detector SDD {self.detector.sdd_mm} mm")

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
