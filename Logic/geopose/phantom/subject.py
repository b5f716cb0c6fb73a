"""Phantom subjects: the CTA and label map on a native grid, the canonical frame,
the arterial centerlines and the exact native-to-canonical transform.

Frames (mm, RAS axes: +x patient right, +y anterior, +z superior):

* *head*: the anatomy's own frame, origin at the centre of the brain.
* *canonical*: the head frame shifted so that the canonical grid (a cube of
  ``CANONICAL_FOV_MM`` centred on the head and upper neck) has its centre at the
  origin: ``x_canonical = x_head - CANONICAL_CENTRE_HEAD_MM``. It is also the
  centred frame of the canonical CTA.
* *centred native*: the centred frame of the subject's CTA (RAS axes, origin at
  the voxel-grid centre, docs/conventions.md section 1). The head sits in it rotated by
  up to ``max_rotation_deg`` and shifted.

``native_to_canonical`` (4x4) maps centred-native points to canonical points:
``x_canonical = native_to_canonical @ x_native``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..volume import Volume
from . import labels as L
from .anatomy import HeadParams, rasterise_head, sample_head
from .raster import Grid

__all__ = ["Subject", "make_subject", "CANONICAL_FOV_MM", "CANONICAL_CENTRE_HEAD_MM"]

#: Edge length (mm) of the default native and canonical fields of view.
CANONICAL_FOV_MM = 256.0
#: Head-frame position (mm) of the canonical grid centre: the cube reaches from
#: above the vertex to the lower neck.
CANONICAL_CENTRE_HEAD_MM = np.array([0.0, 0.0, -36.0])
#: Head-frame point (mm) that C-arm acquisitions are centred on (mid-cranium, a bit low).
ISOCENTRE_HEAD_MM = np.array([0.0, 0.0, -12.0])
#: Largest voxel count make_subject accepts (a 0.5 mm cube of 256 mm is 134 M).
MAX_VOXELS = 160_000_000


def _translation(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _random_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = math.radians(rng.uniform(0.0, max_deg))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _centred_grid(shape_ijk, spacing) -> np.ndarray:
    """ijk -> centred mm for an axis-aligned grid."""
    m = np.diag([*spacing, 1.0])
    m[:3, 3] = -(np.asarray(shape_ijk) - 1) / 2.0 * np.asarray(spacing)
    return m


@dataclass
class Subject:
    """One phantom subject. ``cta`` (HU) and ``labels`` (uint8, see ``labels``) share the
    native grid; ``centerlines`` (arteries: ``name``, ``label``, ``points_mm``, ``radii_mm``,
    ``lumen_hu``) are in the centred native frame (mm)."""

    seed: int
    params: HeadParams
    cta: Volume
    labels: Volume
    centerlines: list[dict]
    native_to_canonical: np.ndarray
    _canonical: dict = field(default_factory=dict, repr=False)

    @property
    def head_to_native(self) -> np.ndarray:
        """4x4 from head coordinates to the centred native frame."""
        return np.linalg.inv(self.native_to_canonical) @ _translation(-CANONICAL_CENTRE_HEAD_MM)

    @property
    def isocentre_native_mm(self) -> np.ndarray:
        """Centred-native position (mm) of the nominal C-arm isocentre of this head."""
        return (self.head_to_native @ np.append(ISOCENTRE_HEAD_MM, 1.0))[:3]

    def canonical(self, spacing_mm: float | None = None) -> tuple[Volume, Volume]:
        """CTA and labels rasterised directly in the canonical frame (a cube of
        ``CANONICAL_FOV_MM``, default spacing = the native one's smallest); cached."""
        sp = float(spacing_mm or min(self.cta.spacing_mm))
        if sp not in self._canonical:
            n = int(round(CANONICAL_FOV_MM / sp))
            ijk_to_can = _centred_grid((n, n, n), (sp, sp, sp))
            grid = Grid((n, n, n), _translation(CANONICAL_CENTRE_HEAD_MM) @ ijk_to_can)
            hu, lab = rasterise_head(self.params, grid)
            meta = {"frame": "canonical", "seed": self.seed}
            self._canonical[sp] = (Volume(hu, ijk_to_can, meta), Volume(lab, ijk_to_can.copy(), meta))
        return self._canonical[sp]

    def canonical_cta(self, spacing_mm: float | None = None) -> Volume:
        """The CTA (HU) in the canonical frame; its centred frame is the canonical frame."""
        return self.canonical(spacing_mm)[0]

    def centerline(self, name_prefix: str) -> list[dict]:
        return [c for c in self.centerlines if c["name"].startswith(name_prefix)]

    def truth(self) -> dict:
        """The ground-truth record (JSON-ready) of the volume and its frames."""
        return {
            "seed": self.seed,
            "native_to_canonical": self.native_to_canonical.tolist(),
            "native_to_canonical_doc": "4x4 mapping points in the centred native CTA frame (RAS axes, origin at the "
            "voxel-grid centre, mm) to the canonical frame (RAS axes, mm); x_canonical = M @ x_native",
            "native_rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(self.native_to_canonical[:3, :3]) - 1) / 2, -1, 1)))),
            "ijk_to_ras": self.cta.ijk_to_ras.tolist(),
            "shape_ijk": list(self.cta.shape_ijk),
            "spacing_mm": list(self.cta.spacing_mm),
            "isocentre_native_mm": self.isocentre_native_mm.tolist(),
            "labels": {name: value for value, name in L.LABEL_NAMES.items()},
            "intracranial_offset": L.INTRACRANIAL_OFFSET,
            "label_groups": L.label_groups(),
            "circle_of_willis": dict(self.params.cow),
            "hu": dict(self.params.hu),
            "noise_sd_hu": self.params.noise_sd_hu,
            "lumen_hu_range": [float(min(a["hu"].min() for a in self.params.arteries)),
                               float(max(a["hu"].max() for a in self.params.arteries))],
            "enhancement": self.params.enhancement.record,
            "pathology": None if self.params.avm is None else "avm",
            "avm": None if self.params.avm is None else {
                "side": self.params.avm["side"], "radius_mm": self.params.avm["radius_mm"],
                "centre_native_mm": (self.head_to_native @ np.append(self.params.avm["centre_mm"], 1.0))[:3].tolist()},
            "enhancement_doc": "appearance draws (contrast.Enhancement): plaque centres in the head frame (mm, "
            "docs/phantoms.md), HU",
        }


def make_subject(
    seed: int,
    *,
    spacing_mm: float | tuple[float, float, float] = 1.0,
    shape: tuple[int, int, int] | None = None,
    max_rotation_deg: float = 15.0,
    random_grid: bool = False,
    pathology: str | None = None,
) -> Subject:
    """Generate phantom subject ``seed`` (same seed -> identical arrays).

    ``spacing_mm``: voxel size (i, j, k) in mm, a number for isotropic voxels
    (0.5 mm and up). ``shape``: (i, j, k) voxel counts, default a 256 mm field of
    view. ``random_grid`` draws the field of view, neck coverage and an
    anisotropic spacing (thick slices) like a clinical CTA instead. ``pathology``: ``"avm"``
    adds an arteriovenous malformation (``avm``; everything else stays as without it).
    """
    rng = np.random.default_rng(seed)
    params = sample_head(rng, seed, pathology)
    sp = np.broadcast_to(np.asarray(spacing_mm, float), (3,)).copy()
    if random_grid:
        inplane = rng.uniform(0.6, 1.0)
        sp = np.array([inplane, inplane, rng.choice([0.5, 0.625, 1.0, 1.25, 2.0, 2.5])])
        fov = np.array([rng.uniform(200, 250)] * 2 + [rng.uniform(170, 256)])
        shape = tuple(int(v) for v in np.round(fov / sp))
    if not np.all(np.isfinite(sp)) or sp.min() < 0.5 or sp.max() > 5.0:
        raise ValueError(f"spacing_mm must be between 0.5 and 5 mm per axis, got {spacing_mm}")
    if shape is None:
        shape = tuple(int(round(CANONICAL_FOV_MM / s)) for s in sp)
    shape = tuple(int(v) for v in shape)
    if len(shape) != 3 or min(shape) < 8 or int(np.prod(shape)) > MAX_VOXELS:
        raise ValueError(f"shape must be 3 voxel counts >= 8 with at most {MAX_VOXELS} voxels, got {shape}")
    if not 0.0 <= max_rotation_deg <= 45.0:
        raise ValueError(f"max_rotation_deg must be in [0, 45], got {max_rotation_deg}")

    extent = np.asarray(shape) * sp
    R = _random_rotation(rng, max_rotation_deg)
    # where the native grid centre sits on the head: the top of the head stays inside,
    # the neck coverage varies with the field of view
    top = 92.0 * params.scale[2]
    centre_z = min(top + 6.0 - extent[2] / 2.0, rng.uniform(-45.0, -15.0))
    centre_head = np.array([rng.normal(0, 4.0), rng.normal(-4.0, 4.0), centre_z])
    head_from_native = _translation(centre_head) @ np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]])
    native_to_canonical = _translation(-CANONICAL_CENTRE_HEAD_MM) @ head_from_native

    ijk_to_centred = _centred_grid(shape, sp)
    scanner_origin = np.array([rng.normal(0, 15), rng.normal(20, 15), rng.normal(-120, 30)])
    ijk_to_ras = _translation(scanner_origin) @ ijk_to_centred
    grid = Grid((shape[2], shape[1], shape[0]), head_from_native @ ijk_to_centred)
    hu, lab = rasterise_head(params, grid)
    meta = {"frame": "native", "seed": seed, "units": "HU"}
    cta = Volume(hu, ijk_to_ras, meta)
    labels = Volume(lab, ijk_to_ras.copy(), {"frame": "native", "seed": seed})

    native_from_head = np.linalg.inv(head_from_native)
    centerlines = []
    for a in params.arteries:
        pts = a["points"] @ native_from_head[:3, :3].T + native_from_head[:3, 3]
        centerlines.append({"name": a["name"], "label": int(a["label"]), "points_mm": pts, "radii_mm": np.asarray(a["radii"], float),
                            "lumen_hu": np.asarray(a["hu"], float)})
    return Subject(seed, params, cta, labels, centerlines, native_to_canonical)
