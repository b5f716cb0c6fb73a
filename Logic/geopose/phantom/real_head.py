"""A real head CT made into a CTA: the arterial tree of a phantom subject placed inside it.

The tree is the one :func:`~geopose.phantom.vessels.build_arteries` draws for phantom ``seed``
(head frame, mm; ``anatomy``). :func:`fit_head` carries it into the CT: an affine fitted between
the phantom's cranial cavity and the CT's puts the intracranial arteries in the CT's cranial
cavity; below the skull base a shift fitted on the cervical spine moves the neck's arteries onto
the CT's neck (the phantom's neck is not the CT's); what falls outside the CT's field of view is
clipped. Arterial voxels are blended towards the subject's own lumen HU (falling along the tree,
``contrast.lumen_hu``) by their partial-volume coverage, as ``anatomy.rasterise_head`` does.

Frames (mm, RAS axes): the phantom's *head* frame (``anatomy``) and the CT's *centred* frame
(origin at the voxel-grid centre, docs/conventions.md section 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .. import contract as C
from ..cta import cranium_mask_from_cta, load_cta, sitk_from_volume
from ..errors import InputError
from ..geometry.frames import RAS_TO_LPS
from ..volume import Volume
from . import labels as L
from .anatomy import HU_AIR, HeadParams, inside_cavity_margin, rasterise_head, sample_head
from .raster import Grid, rasterise_tube

__all__ = ["HeadFit", "fit_head", "with_arteries", "deformed_head", "load_headsq", "HEADSQ_HU_OFFSET", "HEADSQ_HEADER_FIX"]

#: Voxel size (mm) the fit works at: the CT is block-averaged to about this.
FIT_SPACING_MM = 4.0
#: Brain and CSF (HU): the CT's cranial cavity is the soft tissue in this range inside the cranium mask.
CAVITY_HU = (-30.0, 120.0)
#: Erosion (mm) that parts the brain from soft tissue it touches through foramina; the largest
#: component after it is taken as the brain.
CAVITY_EROSION_MM = 4.0
#: The cavities are compared as signed distance maps clamped to this (mm).
DISTANCE_CLAMP_MM = 20.0
#: A CT voxel below this (HU) holds no measurement (padding, outside the reconstruction circle):
#: air reads about -1000 HU.
UNSCANNED_BELOW_HU = -1100.0
#: Per-axis scales are kept only within this fraction of the common scale: a cavity that the field
#: of view cuts leaves the scale across the cut unconstrained.
MAX_SCALE_SPREAD = 0.15
#: Start search about the match of the cavities' centroids: steps either side for the pitch and the
#: shifts along y and z, and their sizes.
START_STEPS = (2, 3, 8)
START_PITCH_STEP_DEG = 10.0
START_SHIFT_STEP_MM = 10.0
#: Share of the voxels the gradient-descent stages sample (a fixed random draw).
SAMPLED_FRACTION = 0.25
#: Head-frame box (mm, low and high corners) of the phantom's cavity map: head and neck.
HEAD_BOX_MM = ((-130.0, -140.0, -260.0), (130.0, 140.0, 120.0))
#: Head-frame box (mm) of the cervical spine and the tissue around it that the neck shift is fitted on
#: (bone and soft tissue compared in HU clipped to ``NECK_HU``), and the box the phantom's neck is drawn in.
SPINE_BOX_MM = ((-35.0, -45.0, -150.0), (35.0, 6.0, -70.0))
NECK_BOX_MM = ((-70.0, -70.0, -170.0), (70.0, 70.0, -40.0))
NECK_HU = (-200.0, 1000.0)
#: Neck shift search along x and y of the CT's frame (z stays: the vertebrae repeat along it): steps
#: either side and their size.
NECK_STEPS = (4, 8)
NECK_STEP_MM = 3.0
#: Least share of the spine box the CT must measure for a neck shift (a CT of the head alone has none).
NECK_MIN_COVER = 0.5
#: Head-frame heights (mm) over which the neck shift fades in: none above the skull base's underside,
#: all of it from the second cervical vertebra down.
NECK_BLEND_MM = (-70.0, -100.0)
#: Random smooth variants of a real head (:func:`deformed_head`): B-spline control mesh cells per
#: axis, the sd (mm) of each control point's displacement, and the sd of each axis' scale factor.
DEFORM_MESH_CELLS = 3
DEFORM_AMPLITUDE_MM = 4.0
DEFORM_SCALE_SD = 0.05
#: The VTK headsq file stores raw values: HU = value - 1024.
HEADSQ_HU_OFFSET = -1024.0
#: The headsq header puts the head upside down (superior along RAS -z, the face
#: still anterior): a 180 deg turn about the anterior axis makes it a supine head CT.
HEADSQ_HEADER_FIX = np.diag([-1.0, 1.0, -1.0, 1.0])


@dataclass(frozen=True)
class HeadFit:
    """How head-frame points land in the CT (:meth:`to_centred`). ``head_to_centred`` (4x4, head frame
    -> the CT's centred frame, mm) fits the cavities; ``neck_shift_mm`` (centred frame) moves the neck
    below the skull base (``NECK_BLEND_MM``); ``rms_mm``: root mean square difference of the two clamped
    cavity distance maps over the CT's measured field of view; ``per_axis``: whether the per-axis
    scales were kept (else one common scale)."""

    head_to_centred: np.ndarray
    neck_shift_mm: np.ndarray
    rms_mm: float
    per_axis: bool

    @property
    def scales(self) -> np.ndarray:
        """Scales (head -> CT) along the affine's principal axes, largest first."""
        return np.linalg.svd(self.head_to_centred[:3, :3], compute_uv=False)

    def to_centred(self, points: np.ndarray) -> np.ndarray:
        """Centred-frame positions (mm) of head-frame points ``(N, 3)``."""
        top, bottom = NECK_BLEND_MM
        t = np.clip((points[:, 2] - top) / (bottom - top), 0.0, 1.0)
        weight = t * t * (3.0 - 2.0 * t)
        m = self.head_to_centred
        return points @ m[:3, :3].T + m[:3, 3] + weight[:, None] * self.neck_shift_mm

    @property
    def record(self) -> dict:
        """JSON-ready: the affine, the neck shift, the scales and the fit's residual."""
        return {"head_to_centred": self.head_to_centred.tolist(), "neck_shift_mm": self.neck_shift_mm.tolist(),
                "scales": self.scales.tolist(), "per_axis_scales": self.per_axis, "cavity_rms_mm": self.rms_mm}


def _distance(mask: sitk.Image) -> sitk.Image:
    """Signed distance (mm, negative inside) to the surface of ``mask``, clamped to +-DISTANCE_CLAMP_MM."""
    d = sitk.SignedMaurerDistanceMap(mask, insideIsPositive=False, squaredDistance=False, useImageSpacing=True)
    return sitk.Clamp(sitk.Cast(d, sitk.sitkFloat32), sitk.sitkFloat32, -DISTANCE_CLAMP_MM, DISTANCE_CLAMP_MM)


def _centroid_lps(mask: sitk.Image) -> np.ndarray:
    kji = np.argwhere(sitk.GetArrayFromImage(mask) > 0).mean(axis=0)
    return np.asarray(mask.TransformContinuousIndexToPhysicalPoint(kji[::-1].tolist()))


def _ct_images(cta: Volume, cranium: Volume) -> tuple[sitk.Image, sitk.Image, sitk.Image]:
    """The CT's cranial cavity, its measured voxels (uint8) and its HU, block-averaged to about
    ``FIT_SPACING_MM`` (physical space: the centred frame in LPS)."""
    factors = [max(1, round(FIT_SPACING_MM / s)) for s in cta.spacing_mm]
    hu = sitk.BinShrink(sitk_from_volume(Volume(cta.array.astype(np.float32), cta.ijk_to_centred)), factors)
    inside = sitk.BinShrink(sitk_from_volume(Volume(cranium.array.astype(np.float32), cta.ijk_to_centred)), factors)
    soft = (hu > CAVITY_HU[0]) & (hu < CAVITY_HU[1]) & (inside > 0.5)
    radius = [max(1, round(CAVITY_EROSION_MM / s)) for s in hu.GetSpacing()]
    core = sitk.BinaryErode(soft, radius, sitk.sitkBall)
    largest = sitk.RelabelComponent(sitk.ConnectedComponent(core), sortByObjectSize=True) == 1
    cavity = sitk.BinaryFillhole(sitk.BinaryDilate(largest, radius, sitk.sitkBall) & soft)
    if not np.any(sitk.GetArrayFromImage(cavity)):
        raise InputError("no cranial cavity found in the CT (no brain-like HU inside its cranium mask): "
                         "arteries cannot be placed")
    return cavity, sitk.Cast(hu >= UNSCANNED_BELOW_HU, sitk.sitkUInt8), hu


def _box_grid(box: tuple) -> Grid:
    """A ``FIT_SPACING_MM`` grid over a head-frame box ``(low corner, high corner)`` (mm)."""
    lo, hi = (np.asarray(c) for c in box)
    n = np.floor((hi - lo) / FIT_SPACING_MM).astype(int) + 1
    ijk_to_head = np.diag([FIT_SPACING_MM] * 3 + [1.0])
    ijk_to_head[:3, 3] = lo
    return Grid((n[2], n[1], n[0]), ijk_to_head)


def _phantom_cavity(params: HeadParams) -> sitk.Image:
    """The phantom's cranial cavity (uint8) over ``HEAD_BOX_MM`` (physical space: the head frame in LPS)."""
    grid = _box_grid(HEAD_BOX_MM)
    x, y, z = grid.coords
    depth = inside_cavity_margin(params, np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1) / params.scale)
    return sitk_from_volume(Volume((depth > 0).reshape(x.shape).astype(np.uint8), grid.ijk_to_head))


def _matrix(transform: sitk.Transform) -> np.ndarray:
    """A SimpleITK matrix-offset transform (fixed LPS -> moving LPS) as a 4x4 in RAS."""
    a = np.asarray(transform.GetMatrix()).reshape(3, 3)
    c = np.asarray(transform.GetCenter())
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = c + np.asarray(transform.GetTranslation()) - a @ c
    return RAS_TO_LPS @ m @ RAS_TO_LPS


def _register(fixed: sitk.Image, moving: sitk.Image, mask: sitk.Image, transform, *,
              search: tuple[tuple, tuple] | None = None, after: sitk.Transform | None = None,
              weights: tuple | None = None) -> float:
    """Mean squares of ``fixed`` and ``moving`` over the ``mask`` voxels of ``fixed``, optimised in place
    from ``transform`` (followed by ``after``, if given, into ``moving``): an exhaustive search (``search``:
    steps either side and step sizes per parameter) at 2x, else gradient descent at 2x and 1x (``weights``
    per parameter, 0 holds one); the final value."""
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMeanSquares()
    reg.SetMetricFixedMask(mask)
    reg.SetInterpolator(sitk.sitkLinear)
    if search is not None:
        reg.SetOptimizerAsExhaustive(list(search[0]))
        reg.SetOptimizerScales(list(search[1]))
        reg.SetShrinkFactorsPerLevel([2])
        reg.SetSmoothingSigmasPerLevel([1.0])
    else:
        reg.SetMetricSamplingStrategy(reg.RANDOM)
        reg.SetMetricSamplingPercentage(SAMPLED_FRACTION, 1)
        reg.SetOptimizerAsRegularStepGradientDescent(learningRate=1.0, minStep=1e-2, numberOfIterations=200,
                                                     relaxationFactor=0.7)
        reg.SetOptimizerScalesFromPhysicalShift()
        if weights is not None:
            reg.SetOptimizerWeights(list(weights))
        reg.SetShrinkFactorsPerLevel([2, 1])
        reg.SetSmoothingSigmasPerLevel([1.0, 0.0])
    if after is not None:
        reg.SetMovingInitialTransform(after)
    reg.SetInitialTransform(transform, inPlace=True)
    reg.Execute(fixed, moving)
    return float(reg.GetMetricValue())


def _neck_shift(hu: sitk.Image, params: HeadParams, head_to_centred: np.ndarray) -> np.ndarray:
    """The shift (mm, centred frame) that lays the phantom's cervical spine, placed by ``head_to_centred``,
    onto the CT's (``hu``: its block-averaged HU); zero where the CT holds too little of the neck."""
    centred_to_head = np.linalg.inv(head_to_centred)
    k, j, i = np.indices(hu.GetSize()[::-1]).reshape(3, -1)
    ijk_to_lps = np.reshape(hu.GetDirection(), (3, 3)) * hu.GetSpacing()
    ras = (np.stack([i, j, k], axis=1) @ ijk_to_lps.T + hu.GetOrigin()) @ RAS_TO_LPS[:3, :3]
    head = ras @ centred_to_head[:3, :3].T + centred_to_head[:3, 3]
    lo, hi = (np.asarray(c) for c in SPINE_BOX_MM)
    values = sitk.GetArrayFromImage(hu).ravel()
    inside = np.all((head > lo) & (head < hi), axis=1) & (values >= UNSCANNED_BELOW_HU)
    box_voxels = np.prod(hi - lo) * abs(np.linalg.det(head_to_centred[:3, :3])) / np.prod(hu.GetSpacing())
    if inside.sum() < NECK_MIN_COVER * box_voxels:
        return np.zeros(3)
    mask = sitk.GetImageFromArray(inside.reshape(hu.GetSize()[::-1]).astype(np.uint8))
    mask.CopyInformation(hu)
    grid = _box_grid(NECK_BOX_MM)
    neck, _ = rasterise_head(params, grid)
    moving = sitk_from_volume(Volume(np.clip(neck, *NECK_HU), grid.ijk_to_head))
    placed = sitk.AffineTransform(3)
    lps_map = RAS_TO_LPS @ centred_to_head @ RAS_TO_LPS
    placed.SetMatrix(lps_map[:3, :3].ravel().tolist())
    placed.SetTranslation(lps_map[:3, 3].tolist())
    fixed = sitk.Clamp(hu, sitk.sitkFloat32, *NECK_HU)
    shift = sitk.TranslationTransform(3)
    _register(fixed, moving, mask, shift, search=((*NECK_STEPS, 0), (NECK_STEP_MM, NECK_STEP_MM, 1.0)), after=placed)
    _register(fixed, moving, mask, shift, after=placed, weights=(1.0, 1.0, 0.0))
    # the CT point x shows the phantom point placed at x + offset: the phantom moves by -offset
    return -(RAS_TO_LPS[:3, :3] @ np.asarray(shift.GetOffset()))


def fit_head(cta: Volume, cranium: Volume, params: HeadParams) -> HeadFit:
    """How phantom ``params`` lands in ``cta`` (HU; ``cranium`` its cranium mask on the same grid). The
    affine lays the phantom's cranial cavity onto the CT's: signed distance maps of the two compared by
    mean squares over the voxels the CT measured (a cavity the field of view cuts is compared where it is
    seen), in stages: a search of pitch and shifts about the match of the centroids, rigid, one common
    scale, per-axis scales (kept within ``MAX_SCALE_SPREAD`` of the common one). The neck shift then lays
    the phantom's cervical spine onto the CT's (``SPINE_BOX_MM``; HU compared)."""
    cavity, valid, hu = _ct_images(cta, cranium)
    fixed = _distance(cavity)
    phantom = _phantom_cavity(params)
    moving = _distance(phantom)
    centre = _centroid_lps(cavity)
    rigid = sitk.Euler3DTransform()
    rigid.SetCenter(centre.tolist())
    rigid.SetTranslation((_centroid_lps(phantom) - centre).tolist())
    pitch, y, z = START_STEPS  # Euler angles about x, y, z, then shifts along x, y, z
    sizes = (np.radians(START_PITCH_STEP_DEG), 1.0, 1.0, 1.0, START_SHIFT_STEP_MM, START_SHIFT_STEP_MM)
    _register(fixed, moving, valid, rigid, search=((pitch, 0, 0, 0, y, z), sizes))
    _register(fixed, moving, valid, rigid)
    common = sitk.Similarity3DTransform()
    common.SetCenter(rigid.GetCenter())
    common.SetMatrix(rigid.GetMatrix())
    common.SetTranslation(rigid.GetTranslation())
    metric = _register(fixed, moving, valid, common)
    axes = sitk.ScaleVersor3DTransform()
    axes.SetCenter(common.GetCenter())
    axes.SetRotation(common.GetVersor())
    axes.SetTranslation(common.GetTranslation())
    axes.SetScale([common.GetScale()] * 3)
    axes_metric = _register(fixed, moving, valid, axes)
    per_axis = bool(np.all(np.abs(np.asarray(axes.GetScale()) / common.GetScale() - 1.0) <= MAX_SCALE_SPREAD))
    chosen, metric = (axes, axes_metric) if per_axis else (common, metric)
    head_to_centred = np.linalg.inv(_matrix(chosen))
    return HeadFit(head_to_centred, _neck_shift(hu, params, head_to_centred), float(np.sqrt(metric)), per_axis)


def _in_view(cta: Volume, measured: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bool per centred-frame point ``(N, 3)`` (mm): its nearest voxel is on the grid and measured."""
    to_ijk = np.linalg.inv(cta.ijk_to_centred)
    ijk = np.rint(points @ to_ijk[:3, :3].T + to_ijk[:3, 3]).astype(int)
    ok = np.all((ijk >= 0) & (ijk < np.asarray(cta.shape_ijk)), axis=1)
    i, j, k = ijk[ok].T
    ok[ok] = measured[k, j, i]
    return ok


def _clipped(artery: dict, points: np.ndarray, radii: np.ndarray, keep: np.ndarray) -> list[dict]:
    """The runs of two or more consecutive kept points of one artery, as centreline dicts."""
    edges = np.diff(np.concatenate(([0], keep.astype(np.int8), [0])))
    runs = zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))
    return [{"name": artery["name"], "label": int(artery["label"]), "points_mm": points[a:b], "radii_mm": radii[a:b]}
            for a, b in runs if b - a >= 2]


def with_arteries(cta: Volume, seed: int, *, cranium: Volume | None = None) -> tuple[Volume, Volume, list[dict]]:
    """``cta`` (a head CT in HU without contrast; left unchanged) with the arteries of phantom ``seed``
    (:func:`fit_head`): the CTA (HU, float32; every voxel the arteries do not cover keeps its value, covered
    ones are raised towards the subject's lumen HU along each artery, never lowered), its label map (uint8, ``labels``:
    ``CRANIUM`` where ``cranium`` is, default :func:`~geopose.cta.cranium_mask_from_cta`; artery labels,
    plus ``INTRACRANIAL_OFFSET`` inside it) and the artery centrelines in the CT's centred frame
    (``Subject.centerlines``' keys; clipped to the measured field of view). Arteries are painted only
    where the CT shows tissue (above ``HU_AIR_MAX``). The fit is in the CTA's ``metadata["arteries"]``."""
    cranium = cranium_mask_from_cta(cta) if cranium is None else cranium
    params = sample_head(np.random.default_rng(seed), seed)  # subject ``seed`` as make_subject draws it
    fit = fit_head(cta, cranium, params)
    radius_scale = abs(np.linalg.det(fit.head_to_centred[:3, :3])) ** (1.0 / 3.0)
    grid = Grid(cta.array.shape, cta.ijk_to_centred)
    cover = np.zeros(cta.array.shape, np.float32)
    artery = np.zeros(cta.array.shape, np.uint8)
    lumen = np.zeros(cta.array.shape, np.float32)
    measured = cta.array >= UNSCANNED_BELOW_HU
    lines: list[dict] = []
    for a in params.arteries:
        points, radii = fit.to_centred(a["points"]), np.asarray(a["radii"], float) * radius_scale
        rasterise_tube(grid, points, radii, cover, artery, a["label"], values=lumen, point_values=a["hu"])
        lines += _clipped(a, points, radii, _in_view(cta, measured, points))
    air = cta.array <= C.HU_AIR_MAX
    cover[air] = 0.0
    artery[air] = 0
    hu = cta.array.astype(np.float32)
    hu = np.maximum(hu, hu + cover * (lumen - hu))
    inside = cranium.array > 0
    lab = inside.astype(np.uint8) * np.uint8(L.CRANIUM)
    vessel = artery > 0
    lab[vessel] = artery[vessel] + np.where(inside[vessel], L.INTRACRANIAL_OFFSET, 0).astype(np.uint8)
    lumen_hu = np.concatenate([a["hu"] for a in params.arteries])
    record = {"phantom_seed": int(seed), **fit.record, "vessel_hu": float(params.hu["vessel"]),
              "lumen_hu_range": [float(lumen_hu.min()), float(lumen_hu.max())]}
    return (Volume(hu, cta.ijk_to_ras.copy(), {**cta.metadata, "arteries": record}),
            cta.like(lab, kind="labels", arteries=record), lines)


def deformed_head(
    cta: Volume, labels: Volume, seed: int, *, amplitude_mm: float = DEFORM_AMPLITUDE_MM, scale_sd: float = DEFORM_SCALE_SD
) -> tuple[Volume, Volume]:
    """A random smooth variant of a head CT (HU) and its label map, both on the CT's grid (inputs
    unchanged): a scale of each axis about the grid centre (factors 1 + N(0, ``scale_sd``)) then a
    cubic B-spline displacement (``DEFORM_MESH_CELLS`` cells per axis, control points N(0,
    ``amplitude_mm``) mm). Linear for the CT (air outside), nearest neighbour for the labels."""
    if labels.array.shape != cta.array.shape:
        raise InputError(f"labels {labels.array.shape} and CT {cta.array.shape} must share one grid")
    rng = np.random.default_rng(seed)
    image, label_image = sitk_from_volume(cta), sitk_from_volume(labels)
    centre = image.TransformContinuousIndexToPhysicalPoint([(n - 1) / 2.0 for n in image.GetSize()])
    scale = sitk.ScaleTransform(3, [float(f) for f in 1.0 + rng.normal(0.0, scale_sd, 3)])
    scale.SetCenter(centre)
    bspline = sitk.BSplineTransformInitializer(image, [DEFORM_MESH_CELLS] * 3)
    bspline.SetParameters([float(v) for v in rng.normal(0.0, amplitude_mm, len(bspline.GetParameters()))])
    warp = sitk.CompositeTransform([scale, bspline])
    ct = sitk.Resample(image, image, warp, sitk.sitkLinear, HU_AIR)
    lab = sitk.Resample(label_image, label_image, warp, sitk.sitkNearestNeighbor, 0)
    record = {"seed": int(seed), "amplitude_mm": float(amplitude_mm), "scale_sd": float(scale_sd)}
    return (cta.like(sitk.GetArrayFromImage(ct).astype(np.float32), **{**cta.metadata, "deformed": record}),
            labels.like(sitk.GetArrayFromImage(lab).astype(labels.array.dtype), **{**labels.metadata, "deformed": record}))


def load_headsq(path: str | Path) -> Volume:
    """The real head CT ``headsq`` (``quarter_sidecar.mhd``) in HU as a supine head CT: its raw
    values shifted by ``HEADSQ_HU_OFFSET`` and its upside-down header turned by ``HEADSQ_HEADER_FIX``."""
    raw = load_cta(path, hu_offset=HEADSQ_HU_OFFSET)
    return Volume(raw.array, HEADSQ_HEADER_FIX @ raw.ijk_to_ras, dict(raw.metadata, header_fix="180 deg about A"))
