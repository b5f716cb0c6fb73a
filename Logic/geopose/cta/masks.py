"""Masks derived from a CT(A) in HU: the cranium and an approximate vessel mask.

Both are threshold-and-morphology methods (no learning); they are meant for the
DRR label channels and for evaluation on phantoms, not for diagnosis.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import SimpleITK as sitk

from .. import contract as C
from ..volume import Volume
from .arteries import keep_arteries, load_artery_classifier
from .io import sitk_from_volume, sitk_geometry
from ..errors import InputError

__all__ = ["cranium_mask_from_cta", "vessel_mask_from_cta", "vessel_candidates", "CLOSING_RADIUS_MM", "VESSEL_HU_RANGE",
           "DENSE_BONE_HU", "MARROW_MAX_MM2", "BODY_HU", "BODY_SURFACE_MM", "CONTRAST_SPAN_MM"]

#: Radius (mm) of the closing that seals sutures, foramina and thin bone before filling.
CLOSING_RADIUS_MM = 7.0
#: The cranium mask is computed on a grid no finer than this (mm), then mapped back.
WORK_SPACING_MM = 2.0
#: Contrast-filled lumen range (HU) accepted as vessel by the approximate vessel mask.
VESSEL_HU_RANGE = (150.0, 700.0)
#: Dense bone (HU): voxels within :data:`BONE_MARGIN_MM` of it (or of the marrow it rings) are not vessel
#: (partial-volume rim).
DENSE_BONE_HU = 700.0
#: Largest marrow cross-section (mm^2, a hole of dense bone in an axial slice) counted as bone: a vertebral
#: body's core (about 130 mm^2) is, the cranial cavity is not.
MARROW_MAX_MM2 = 400.0
#: The body (head and neck) is HU above this (air is about -1000 HU, fat -100).
BODY_HU = -400.0
#: Depth (mm) below the body's surface at which a vessel may start (skin, holders and tables lie above it).
BODY_SURFACE_MM = 5.0
#: A contrast-filled vessel tree spans at least this along the superior axis (mm); the largest candidate
#: of a CT without contrast (partial-volume bone) spans less (headsq: 57 mm, with arteries 140 mm).
CONTRAST_SPAN_MM = 100.0
BONE_MARGIN_MM = 2.5
#: Lumen inside a bony canal (the ICA through the petrous bone, the vertebral arteries through the transverse
#: foramina) lies within the bone margin; it is taken back where it is a dark tube (Gaussian scale, mm;
#: Frangi measure threshold; tuned on validation phantoms 6000-6003: carotid centreline recall 71-73 -> 82-98 %).
CANAL_SIGMA_MM = 1.5
CANAL_OBJECTNESS = 0.03
CANAL_GRID_MM = 2.0
#: The mouth of a bony canal is near bone without being a tube (bone on one side only), so the canal's tube can lie
#: apart from the tree. Lumen near bone within this (mm) of both the tree and a canal tube bridges the mouth, and a
#: piece of canal so joined is kept where it is a clear tube: its mean tube measure at least
#: :data:`CANAL_CLEAR_OBJECTNESS` (on validation phantoms 6010-6029 the petrous ICA's pieces 0.10-0.16, lumen-HU
#: marrow in bone and veins through foramina 0.03-0.07; experiments/vessel_mask/canal_mouth/canal_mouth.md).
CANAL_MOUTH_MM = 3.0
CANAL_CLEAR_OBJECTNESS = 0.1
#: A clear canal piece is joined to the tree across lumen near bone within this (mm) of both (the petrous ICAs of
#: validation phantoms 6025 and 6032 began 7-8 mm above the neck's tree, and 3 mm left them out); of that wider mouth
#: only the voxels within :data:`CANAL_MOUTH_MM` of both stay in the mask: reached the whole 4 mm, the mouths brought
#: the cavernous sinus and lumen-HU marrow (experiments/vessel_mask/canal_bridge/canal_bridge.md).
CANAL_BRIDGE_MM = 4.0
#: Voxels within this (mm) of air inside the body (the walls of the nasal cavity, paranasal sinuses, pharynx) are not vessel.
AIR_MARGIN_MM = 3.0
#: The vessel mask is computed on a grid no finer than this (mm; HU block-averaged, the cranium
#: mask by majority), then mapped back by nearest neighbour: at 0.5 mm it costs 8 s on 2 cores.
VESSEL_WORK_SPACING_MM = 1.0
#: The artery classifier (``arteries.py``) runs on working grids no coarser than this along any axis (mm): it was
#: trained and validated at 1 mm; on phantom 21 at 2 mm it kept 38 % of the intracranial arteries (the tree 78 %).
ARTERY_CLASSIFIER_MAX_MM = 1.5
#: Vessel components smaller than this (mm^3) are dropped as noise.
MIN_VESSEL_COMPONENT_MM3 = 10.0
#: The vessel mask is worked out on the body's box grown by this (mm): past the body surface margin and the air and
#: bone margins, which then see the background they see on the whole grid, and 5 sigmas of the canal filter's
#: smoothing (:data:`CANAL_SIGMA_MM`). The masks were voxel for voxel those of the whole grid on the 1 mm demo
#: phantom, validation phantoms 6010-6034 and the four real heads (and with a 4 mm margin on 11 of them).
BODY_BOX_MARGIN_MM = 8.0


def _radius_vox(radius_mm: float, spacing_mm: tuple[float, float, float]) -> list[int]:
    return [max(1, int(round(radius_mm / s))) for s in spacing_mm]


def _work_factors(volume: Volume, work_spacing_mm: float) -> list[int]:
    """Block factors (i, j, k) that make ``volume``'s voxels about ``work_spacing_mm`` (1 where finer is not needed)."""
    return [max(1, round(work_spacing_mm / s)) for s in volume.spacing_mm]


def _back_to_full(mask: Volume, volume: Volume) -> np.ndarray:
    """A uint8 mask on a working grid (:meth:`Volume.shrunk` of ``volume``) mapped onto ``volume``'s grid by nearest
    neighbour."""
    if mask.array.shape == volume.array.shape:
        return mask.array.astype(np.uint8, copy=False)
    full = sitk.Resample(sitk_from_volume(mask), transform=sitk.Transform(), interpolator=sitk.sitkNearestNeighbor,
                         defaultPixelValue=0, outputPixelType=sitk.sitkUInt8, **sitk_geometry(volume))
    return sitk.GetArrayFromImage(full)


def _largest_component(mask: sitk.Image) -> sitk.Image:
    cc = sitk.ConnectedComponent(mask, True)
    relabelled = sitk.RelabelComponent(cc, sortByObjectSize=True)
    return sitk.Cast(relabelled == 1, sitk.sitkUInt8)


def _slice_background(mask: np.ndarray, axis: int) -> tuple[np.ndarray, sitk.Image, np.ndarray, np.ndarray]:
    """The background regions of every 2D slice of ``mask`` ([k, j, i] array) taken across ``axis``, in one
    connected-component pass over the slices stacked with an empty separator between them (face connectivity, so no
    region crosses slices). Returns the slices (bool, slice axis first), the component image (it owns the labels'
    memory: keep it while they are used), the labels of the slices (a view, separators left out; 0 = not background)
    and the labels that touch a slice's border (not holes)."""
    slices = np.moveaxis(np.asarray(mask, dtype=bool), axis, 0)
    n, h, w = slices.shape
    background = np.zeros((2 * n - 1, h, w), dtype=np.uint8)
    background[::2] = ~slices
    components = sitk.ConnectedComponent(sitk.GetImageFromArray(background), False)
    labels = sitk.GetArrayViewFromImage(components)[::2]  # a view: no copy of the doubled grid
    border = np.concatenate([labels[:, 0].ravel(), labels[:, -1].ravel(), labels[:, :, 0].ravel(), labels[:, :, -1].ravel()])
    return slices, components, labels, border


def _fill_slicewise(mask: np.ndarray, axis: int) -> np.ndarray:
    """Fill 2D holes in every slice of ``mask`` ([k, j, i] array) taken across ``axis``: background regions that do
    not touch a slice's border (:func:`_slice_background`)."""
    slices, components, labels, border = _slice_background(mask, axis)
    hole = np.ones(int(labels.max()) + 1, dtype=bool)  # per label: a hole (not background, not at a border)
    hole[0] = False
    hole[border] = False
    holes = hole[labels]
    return np.moveaxis(slices | holes, 0, axis).astype(mask.dtype)


def _superior_array_axis(volume: Volume) -> int:
    """Array axis ([k, j, i] order) whose voxel direction is closest to the RAS z axis."""
    z_component = np.abs(volume.ijk_to_ras[2, :3]) / np.asarray(volume.spacing_mm)
    return 2 - int(np.argmax(z_component))


def cranium_mask_from_cta(volume: Volume, *, bone_hu: float = C.HU_BONE_MIN) -> Volume:
    """Skull plus intracranial region as a uint8 {0, 1} label map on the CTA grid.

    Method (on a grid averaged down to voxels of about 2 mm, result mapped back
    by nearest neighbour): (1) bone = HU > ``bone_hu`` (the DRR bone threshold, 350 HU);
    (2) binary closing with a ~7 mm ellipsoid (per-axis radius from the spacing) to seal sutures,
    foramina and thin bone; (3) the largest 26-connected bone component (the skull,
    dropping the table and loose fragments; the cervical spine stays if it touches);
    (4) holes filled in every axial slice (slices across the array axis closest to
    RAS superior), which fills the intracranial space wherever the skull forms a ring,
    then a closing along that axis (bridges slices whose ring has a gap) and a 3D hole
    fill; (5) the largest component again. Facial bones that form rings
    in axial slices (maxilla, mandible) are included with their enclosed cavities.
    """
    if not np.any(volume.array > bone_hu):
        raise InputError(f"no voxel above {bone_hu:g} HU: the CTA shows no bone, so no cranium mask can be derived; supply a mask")
    work = volume.shrunk(_work_factors(volume, WORK_SPACING_MM))
    radius = _radius_vox(CLOSING_RADIUS_MM, work.spacing_mm)
    bone = np.asarray(work.array) > bone_hu
    # the steps below on the bone's box grown past the closing's reach: every slice's rim stays outside the head
    box = _grown_box(bone, [r + 1 for r in radius[::-1]])
    closed = _closed_by_ball(bone[box], radius)
    skull = sitk.GetArrayFromImage(_largest_component(sitk.GetImageFromArray(closed.astype(np.uint8)))).astype(bool)
    axis = _superior_array_axis(volume)
    bridged = _closed_along(_fill_slicewise(skull, axis).astype(bool), axis, radius[2 - axis])
    cranium = _largest_component(sitk.BinaryFillhole(sitk.GetImageFromArray(bridged.astype(np.uint8)), fullyConnected=False))
    mask = np.zeros(bone.shape, np.uint8)
    mask[box] = sitk.GetArrayFromImage(cranium)
    out = _back_to_full(work.like(mask), volume)
    return volume.like(out, kind="cranium_mask", method="bone threshold + closing + largest component + axial fill")


def vessel_mask_from_cta(volume: Volume, *, arteries_only: bool = True) -> Volume:
    """APPROXIMATE contrast-filled vessel mask (uint8 {0, 1}) of the head and neck.

    Voxels in :data:`VESSEL_HU_RANGE` (150..700 HU) inside the body (HU > :data:`BODY_HU`, largest
    component, filled per axial slice, less its outer :data:`BODY_SURFACE_MM`: the neck's carotid and
    vertebral arteries that every run shows are in it), more than :data:`AIR_MARGIN_MM` from air inside
    the body (the thin walls of the nasal cavity and sinuses) and more than :data:`BONE_MARGIN_MM` from bone:
    dense bone (> :data:`DENSE_BONE_HU`) together with the marrow it rings in an axial slice (holes up to
    :data:`MARROW_MAX_MM2`; a bone core of lumen HU is no vessel); connected components of at least
    :data:`MIN_VESSEL_COMPONENT_MM3`. Lumen within the bone margin is taken back where it is a dark tube
    (a bony canal: the petrous ICA, the vertebral arteries in the transverse foramina) connected to that
    tree (:func:`_tube_measure`), or bridged to it across the canal's mouth where the piece is shaped like a vessel
    (:func:`_canal_mouths`). Of that tree, ``arteries_only`` keeps the voxels the artery classifier
    (``arteries.py``) calls artery where the working grid is no coarser than :data:`ARTERY_CLASSIFIER_MAX_MM`: the
    venous sinuses, jugular veins and rims leave (held-out phantoms 5000-5019 at 1 mm: precision 89 %, carotid
    centreline recall 96 %, at the classifier's p >= 0.3). On a CTA finer than :data:`VESSEL_WORK_SPACING_MM` all of
    it on a working grid of that size. An approximation, never a segmentation.

    A CT without contrast has no vessel tree: when no component spans :data:`CONTRAST_SPAN_MM` along
    the superior axis the mask is empty, ``metadata["contrast"]`` is
    False and ``method`` says so (a registration then runs without the vessel term).
    """
    work, tree, span_mm = vessel_candidates(volume)
    method = "approximate: contrast HU range in the head and neck away from bone and marrow"
    if work is not volume:
        method += f", on a {VESSEL_WORK_SPACING_MM:g} mm working grid"
    if span_mm < CONTRAST_SPAN_MM:
        return volume.like(np.zeros(volume.array.shape, np.uint8), kind="vessel_mask", contrast=False,
                           method=f"{method}: no contrast-filled vessel tree (the longest candidate spans {span_mm:.0f} mm "
                                  f"< {CONTRAST_SPAN_MM:g} mm; CT without contrast?), empty")
    metadata = {}
    if arteries_only and max(work.spacing_mm) > ARTERY_CLASSIFIER_MAX_MM:
        method += (f"; no artery classifier (a {max(work.spacing_mm):g} mm working grid, coarser than the "
                   f"{ARTERY_CLASSIFIER_MAX_MM:g} mm it is made for): veins included")
    elif arteries_only:
        classifier = load_artery_classifier()
        tree, share = keep_arteries(work, tree, np.asarray(cranium_mask_from_cta(work).array) > 0, classifier)
        method += (f"; of it the {100 * share:.0f} % a classifier calls artery (artery_classifier.json sha256 "
                   f"{classifier.sha256[:12]}, p >= {classifier.threshold:g})")
        metadata = {"artery_share": share, "artery_classifier_sha256": classifier.sha256}
    out = _back_to_full(work.like(tree.astype(np.uint8)), volume)
    return volume.like(out, kind="vessel_mask", contrast=True, method=method, **metadata)


def vessel_candidates(volume: Volume) -> tuple[Volume, np.ndarray, float]:
    """The contrast-threshold tree of :func:`vessel_mask_from_cta` before the artery classifier: the working grid
    (``volume`` itself unless finer than :data:`VESSEL_WORK_SPACING_MM`), the tree on it ([k, j, i] bool) and the
    longest extent (mm) of one of its components along the superior axis."""
    axis = _superior_array_axis(volume)
    factors = _work_factors(volume, VESSEL_WORK_SPACING_MM)
    work = volume.shrunk(factors, np.float32) if max(factors) > 1 else volume
    tree, span_mm = _vessel_mask(np.asarray(work.array, dtype=np.float32), work.spacing_mm, axis)
    return work, tree > 0, span_mm


def _dilate_mm(mask: np.ndarray, radius_mm: float, spacing_mm) -> np.ndarray:
    """``mask`` ([k, j, i] bool) dilated by a ball of ``radius_mm`` (per-axis radius from ``spacing_mm``, i, j, k),
    worked out on the mask's box grown by the radius (the air inside a head fills a small part of it)."""
    radius = _radius_vox(radius_mm, spacing_mm)
    out = np.zeros(mask.shape, dtype=bool)
    box = _grown_box(mask, radius[::-1])
    if box is not None:
        image = sitk.GetImageFromArray(mask[box].astype(np.uint8))
        out[box] = sitk.GetArrayFromImage(sitk.BinaryDilate(image, radius, sitk.sitkBall)) > 0
    return out


def _grown_box(mask: np.ndarray, grow: Sequence[int], block: Sequence[int] = (1, 1, 1)) -> tuple[slice, ...] | None:
    """The index box ([k, j, i] slices) of ``mask``'s voxels grown by ``grow`` voxels per array axis and clipped to the
    grid, each start a whole number of ``block`` voxels; None when the mask is empty."""
    box = []
    for axis, (n, g, b) in enumerate(zip(mask.shape, grow, block)):
        present = np.flatnonzero(mask.any(axis=tuple(x for x in range(mask.ndim) if x != axis)))
        if not len(present):
            return None
        box.append(slice(max(0, int(present[0]) - g) // b * b, min(n, int(present[-1]) + 1 + g)))
    return tuple(box)


def _eroded_by_ball(mask: np.ndarray, radius_vox: list[int]) -> np.ndarray:
    """``mask`` ([k, j, i] bool) eroded by ``sitk.BinaryErode``'s ball of ``radius_vox`` (i, j, k), voxel for
    voxel (outside the grid counts as inside), from a Euclidean distance map in the units of that ball's
    radii (``r + 0.5`` voxels per axis): at 1 mm, 256^3, radius 5: 0.5 s against the filter's 1.1 s."""
    outside = sitk.GetImageFromArray((~np.asarray(mask, dtype=bool)).astype(np.uint8))
    outside.SetSpacing([1.0 / (r + 0.5) for r in radius_vox])
    d2 = sitk.SignedMaurerDistanceMap(outside, insideIsPositive=False, squaredDistance=True, useImageSpacing=True)
    return sitk.GetArrayFromImage(d2) >= 1.0


def _closed_by_ball(mask: np.ndarray, radius_vox: list[int]) -> np.ndarray:
    """``mask`` ([k, j, i] bool) closed by ``sitk.BinaryMorphologicalClosing``'s ball of ``radius_vox`` (i, j, k), voxel
    for voxel (its safe border: no foreground enters from outside the grid): a dilation and an erosion, each from one
    distance map (:func:`_eroded_by_ball`) on the grid padded by the radius. At 2 mm, 128^3, radius 4: 0.21 s against
    the filter's 0.40 s."""
    padded = np.pad(np.asarray(mask, dtype=bool), [(r, r) for r in radius_vox[::-1]])
    inner = tuple(slice(r, r + n) for r, n in zip(radius_vox[::-1], mask.shape))
    return _eroded_by_ball(~_eroded_by_ball(~padded, radius_vox), radius_vox)[inner]


def _closed_along(mask: np.ndarray, axis: int, radius: int) -> np.ndarray:
    """``mask`` ([k, j, i] bool) closed by a line of ``2 radius + 1`` voxels along array ``axis``, voxel for voxel
    ``sitk.BinaryMorphologicalClosing`` with that box (safe border): the maximum, then the minimum, of shifted
    copies. At 2 mm, 128^3, radius 4: a tenth of the filter's 0.27 s."""
    n, width = mask.shape[axis], 2 * radius + 1
    padding = [(0, 0)] * mask.ndim
    padding[axis] = (2 * radius, 2 * radius)
    padded = np.pad(np.asarray(mask, dtype=bool), padding)

    def shifted(a: np.ndarray, start: int, length: int) -> np.ndarray:
        index = [slice(None)] * a.ndim
        index[axis] = slice(start, start + length)
        return a[tuple(index)]

    dilated = np.logical_or.reduce([shifted(padded, s, n + 2 * radius) for s in range(width)])
    return np.logical_and.reduce([shifted(dilated, s, n) for s in range(width)])


def _small_holes_slicewise(mask: np.ndarray, axis: int, max_voxels: float) -> np.ndarray:
    """The 2D holes of at most ``max_voxels`` voxels in every slice of ``mask`` ([k, j, i] bool) taken
    across ``axis`` (as :func:`_fill_slicewise`, holes only, size-limited)."""
    _, components, labels, border = _slice_background(mask, axis)
    sizes = sitk.LabelShapeStatisticsImageFilter()  # voxel counts per label, without a copy of the doubled grid
    sizes.Execute(components)
    small = np.zeros(max(sizes.GetLabels(), default=0) + 1, dtype=bool)  # label 0 (not background) is never a hole
    for label in sizes.GetLabels():
        small[label] = sizes.GetNumberOfPixels(label) <= max_voxels
    small[border] = False
    return np.moveaxis(small[labels], 0, axis)


def _vessel_mask(a: np.ndarray, spacing_mm, axis: int) -> tuple[np.ndarray, float]:
    """The rule of :func:`vessel_mask_from_cta` on one grid: ``a`` HU ``[k, j, i]``, voxel sizes
    ``spacing_mm`` (i, j, k), ``axis`` the superior array axis; uint8 {0, 1} mask and the longest extent
    (mm) of one of its components along ``axis``. Every vessel lies in the body, so the work after finding the body
    is done on the body's box (:func:`_body_box`): on the 1 mm demo phantom 2.4 s instead of 3.7 s (1.9 s with each
    dilation on its own box, :func:`_dilate_mm`)."""
    body = sitk.GetArrayFromImage(_largest_component(sitk.GetImageFromArray((a > BODY_HU).astype(np.uint8)))).astype(bool)
    box = _body_box(body, spacing_mm)
    mask = np.zeros(a.shape, np.uint8)
    mask[box], span_mm = _vessel_mask_in_body(a[box], body[box], spacing_mm, axis)
    return mask, span_mm


def _body_box(body: np.ndarray, spacing_mm) -> tuple[slice, ...]:
    """The index box ([k, j, i] slices) of ``body`` grown by :data:`BODY_BOX_MARGIN_MM` (past every margin the mask
    rule measures from outside the body, and the canal filter's reach), its start a whole number of the canal grid's
    blocks (:func:`_tube_measure` then sees the blocks the whole grid has); the whole grid when there is no body."""
    steps = [float(spacing_mm[2 - axis]) for axis in range(body.ndim)]
    box = _grown_box(body, [int(np.ceil(BODY_BOX_MARGIN_MM / s)) for s in steps],
                     [max(1, round(CANAL_GRID_MM / s)) for s in steps])
    return box if box is not None else tuple(slice(0, n) for n in body.shape)


def _vessel_mask_in_body(a: np.ndarray, body: np.ndarray, spacing_mm, axis: int) -> tuple[np.ndarray, float]:
    """:func:`_vessel_mask` on a box around the body: ``a`` HU and ``body`` (bool, the largest component above
    :data:`BODY_HU`) on it."""
    body = _fill_slicewise(body, axis).astype(bool)
    # air inside the head (nasal cavity, paranasal sinuses, pharynx): its thin bony walls blur into the lumen range
    near_air = _dilate_mm(body & (a < BODY_HU), AIR_MARGIN_MM, spacing_mm)
    # lumen lies below the skin: what is in the lumen range at the body's surface is skin, a head holder or a table
    body = _eroded_by_ball(body, _radius_vox(BODY_SURFACE_MM, spacing_mm))
    in_plane_mm2 = float(np.prod([s for n, s in enumerate(spacing_mm) if n != 2 - axis]))
    bone = a > DENSE_BONE_HU
    bone |= _small_holes_slicewise(bone, axis, MARROW_MAX_MM2 / in_plane_mm2)
    near_bone = _dilate_mm(bone, BONE_MARGIN_MM, spacing_mm)
    lo, hi = VESSEL_HU_RANGE
    lumen_hu = (a >= lo) & (a <= hi) & body & ~near_air
    candidate = lumen_hu & ~near_bone
    min_voxels = max(1, int(np.ceil(MIN_VESSEL_COMPONENT_MM3 / float(np.prod(spacing_mm)))))
    tree = sitk.GetArrayFromImage(sitk.RelabelComponent(
        sitk.ConnectedComponent(sitk.GetImageFromArray(candidate.astype(np.uint8)), True), minimumObjectSize=min_voxels)) > 0
    tubes = _tube_measure(a, spacing_mm)
    canal = lumen_hu & near_bone & (tubes > CANAL_OBJECTNESS)
    bridged, mouths = _canal_mouths(tree, canal, tubes, lumen_hu & near_bone, spacing_mm)
    labels = _joined_components(tree, canal | bridged)
    labels[bridged & ~canal & ~mouths] = 0  # the wider mouths join a canal piece; they are not lumen
    shapes = sitk.LabelShapeStatisticsImageFilter()
    shapes.Execute(sitk.GetImageFromArray(labels))
    dim = 2 - axis  # the superior axis as an (i, j, k) index
    span_vox = max((shapes.GetBoundingBox(label)[3 + dim] for label in shapes.GetLabels()), default=0)
    return (labels > 0).astype(np.uint8), float(span_vox * spacing_mm[dim])


def _tube_measure(a: np.ndarray, spacing_mm) -> np.ndarray:
    """Frangi's tube measure of lumen darker than the bone around it ([k, j, i] float32; ``sitk.ObjectnessMeasure``,
    dark tubes) of the HU smoothed at :data:`CANAL_SIGMA_MM`, bone clipped at 1200 HU so cortex of any density makes
    the same wall. Computed on a grid of about :data:`CANAL_GRID_MM` (a canal's lumen is 4-5 mm wide) and mapped back
    by nearest neighbour: at 1 mm the full grid took 3 s of a 7 s mask on 2 cores."""
    image = sitk.GetImageFromArray(np.clip(a, -200.0, 1200.0).astype(np.float32))
    image.SetSpacing(tuple(float(s) for s in spacing_mm))
    factors = [max(1, round(CANAL_GRID_MM / s)) for s in spacing_mm]
    coarse = sitk.BinShrink(image, factors) if max(factors) > 1 else image
    smooth = sitk.SmoothingRecursiveGaussian(coarse, CANAL_SIGMA_MM)
    tubes = sitk.ObjectnessMeasure(smooth, alpha=0.5, beta=0.5, gamma=100.0, scaleObjectnessMeasure=False,
                                   objectDimension=1, brightObject=False)
    if coarse is not image:
        tubes = sitk.Resample(tubes, image, sitk.Transform(), sitk.sitkNearestNeighbor, 0.0, sitk.sitkFloat32)
    return sitk.GetArrayFromImage(tubes)


def _canal_mouths(tree: np.ndarray, canal: np.ndarray, tubes: np.ndarray, near_bone_lumen: np.ndarray,
                  spacing_mm) -> tuple[np.ndarray, np.ndarray]:
    """The canal tubes bridged to the tree across their mouths, and the mouths that are lumen ([k, j, i] bool, the
    arguments on one grid, bool but ``tubes``, the tube measure): the pieces of ``canal`` together with the
    ``near_bone_lumen`` within :data:`CANAL_BRIDGE_MM` of both it and ``tree`` whose canal voxels' mean tube measure is at
    least :data:`CANAL_CLEAR_OBJECTNESS`; of that lumen, the voxels within :data:`CANAL_MOUTH_MM` of both."""
    near_tree, near_canal = (_dilate_mm(m, CANAL_BRIDGE_MM, spacing_mm) for m in (tree, canal))
    wide = near_bone_lumen & near_tree & near_canal
    pieces = sitk.GetArrayFromImage(sitk.ConnectedComponent(sitk.GetImageFromArray((canal | wide).astype(np.uint8)), True))
    in_canal, count = pieces[canal], int(pieces.max()) + 1
    voxels = np.bincount(in_canal, minlength=count)
    keep = (voxels > 0) & (np.bincount(in_canal, weights=tubes[canal], minlength=count) >= CANAL_CLEAR_OBJECTNESS * voxels)
    keep[0] = False
    bridged = keep[pieces]
    mouths = bridged & wide & _dilate_mm(tree, CANAL_MOUTH_MM, spacing_mm) & _dilate_mm(canal, CANAL_MOUTH_MM, spacing_mm)
    return bridged, mouths


def _joined_components(tree: np.ndarray, canal: np.ndarray) -> np.ndarray:
    """The 26-connected components (uint32 labels, [k, j, i]; 0 elsewhere) of ``tree`` together with the parts
    of ``canal`` connected to it (both bool)."""
    cc = sitk.GetArrayFromImage(sitk.ConnectedComponent(sitk.GetImageFromArray((tree | canal).astype(np.uint8)), True))
    keep = np.zeros(int(cc.max()) + 1, dtype=bool)
    keep[np.unique(cc[tree])] = True
    keep[0] = False
    return np.where(keep[cc], cc, 0).astype(np.uint32)
