"""EXPERIMENTAL, not the default: contrast-filled artery segmentation of a CTA (HU) by multiscale
Hessian objectness on a coarse working grid, trees seeded by long tubes away from bone, delineated
at half maximum on a finer grid. Measured against phantom truth in docs/vessel_segmentation.md: it
does not yet reach the targets of issue 30 (carotid centreline recall >= 95 %, precision >= 80 %),
so ``prepare_case`` still uses ``masks.vessel_mask_from_cta``.

What it computes:

1. *lumen image* (on the tube grid, HU block-averaged to about :data:`TUBE_SPACING_MM`): HU mapped
   through a tent (:func:`lumen_image`) that rises with HU up to :data:`LUMEN_PEAK_HU` and falls back
   to 0 at :data:`BONE_HU`: contrast-filled lumen is bright, cortical bone and dense calcification
   dark, so a lumen inside a bony canal stays a bright tube;
2. *tubularity*: ``sitk.ObjectnessMeasure`` (Frangi's measure of bright lines) of the lumen image
   smoothed at each of :data:`SCALES_MM` (scale-normalised Hessian), the maximum over scales (0..1);
3. *candidates*: HU in :data:`LUMEN_HU`, not enclosed by cortex (3D hole fill of HU >
   :data:`CORTEX_HU`: cancellous bone), not in a structure holding a ball of :data:`THICK_MM`
   (vertebral bodies, jugular veins), and tubularity above :data:`OBJECTNESS_LOW` (above
   :data:`OBJECTNESS_NEAR_BONE` within :data:`BONE_MARGIN_MM` of HU > :data:`BONE_HU`);
4. *trees*: 26-connected candidate components of at least :data:`MIN_TREE_MM3` that hold a seed (a
   tube away from bone with tubularity above :data:`OBJECTNESS_SEED`, at least :data:`MIN_SEED_MM3`,
   spanning :data:`SEED_SPAN_MM` along the slice axis: the neck's arteries);
5. *lumen* (on a grid of about :data:`LUMEN_SPACING_MM`): voxels within :data:`GROW_MM` of the trees
   above half way from :data:`SOFT_TISSUE_HU` to the local lumen peak and below :data:`BONE_HU`;
   mapped back onto the CTA grid by nearest neighbour.

A CT without contrast has no such trees: the mask is then empty and says so (``metadata["contrast"]
False``).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from ..volume import Volume
from .io import sitk_from_volume

__all__ = ["artery_mask_from_cta", "lumen_image", "tubularity", "LUMEN_HU", "TUBE_SPACING_MM", "LUMEN_SPACING_MM"]

#: Tubularity is computed on a grid no finer than this (mm; HU block-averaged).
TUBE_SPACING_MM = 2.0
#: The lumen is delineated on a grid no finer than this (mm).
LUMEN_SPACING_MM = 1.0
#: HU of contrast-filled lumen (after block averaging).
LUMEN_HU = (150.0, 700.0)
#: The lumen image rises with HU up to this peak ...
LUMEN_PEAK_HU = 600.0
#: ... and falls back to 0 at this HU (cortical bone, dense calcification and above stay 0).
BONE_HU = 1100.0
#: Bone cortex (HU): what it encloses (cancellous bone, marrow) is bone too, a canal open at its ends is not.
CORTEX_HU = 700.0
#: Bright structures holding a ball of this radius (mm) are too thick for an artery (vertebral
#: bodies, jugular veins, sinuses of the face).
THICK_MM = 3.0
#: HU of the tissue around the vessels (the half-maximum edge lies half way to the lumen).
SOFT_TISSUE_HU = 40.0
#: Gaussian scales (mm) of the Hessian: vessel radii about 1 to 4 mm.
SCALES_MM = (1.0, 1.6, 2.6)
#: Frangi parameters of ``sitk.ObjectnessMeasure``: plate-vs-line (alpha), blob-vs-line (beta),
#: structure (gamma, in the scale-normalised lumen image's units, HU).
ALPHA, BETA, GAMMA_HU = 0.5, 0.5, 60.0
#: Tubularity (0..1) a tree voxel exceeds; within :data:`BONE_MARGIN_MM` of bone (HU above
#: :data:`BONE_HU`) it must exceed :data:`OBJECTNESS_NEAR_BONE` (a lumen in a bony canal).
OBJECTNESS_LOW = 0.2
OBJECTNESS_NEAR_BONE = 0.5
BONE_MARGIN_MM = 3.0
#: Seeds: voxels away from bone with tubularity above this, in tubes of at least :data:`MIN_SEED_MM3`;
#: a tree is kept only if it holds one.
OBJECTNESS_SEED = 0.4
MIN_SEED_MM3 = 150.0
#: ... that span at least this along the slice axis (mm): the neck's arteries run up the neck.
SEED_SPAN_MM = 20.0
#: A kept tree has at least this volume (mm^3).
MIN_TREE_MM3 = 200.0
#: Percentile of a tree's HU reported as its lumen HU (``metadata["trees"]``).
TREE_HU_PERCENTILE = 90.0
#: The lumen reaches this far (mm) from the trees' voxels.
GROW_MM = 1.0


def lumen_image(hu: np.ndarray) -> np.ndarray:
    """The tent map of HU (float32): 0 at or below 0 HU, ``hu`` up to :data:`LUMEN_PEAK_HU`, then
    linearly down to 0 at :data:`BONE_HU` and beyond."""
    hu = np.asarray(hu, np.float32)
    rise = np.clip(hu, 0.0, LUMEN_PEAK_HU)
    fall = LUMEN_PEAK_HU * np.clip((BONE_HU - hu) / (BONE_HU - LUMEN_PEAK_HU), 0.0, 1.0)
    return np.minimum(rise, fall).astype(np.float32)


def tubularity(lumen: sitk.Image) -> sitk.Image:
    """Maximum over :data:`SCALES_MM` (those of at least 0.5 voxel) of the scale-normalised Frangi
    objectness of bright lines in ``lumen`` (float image); 0..1."""
    finest = 0.5 * min(lumen.GetSpacing())
    best = None
    for sigma in (s for s in SCALES_MM if s >= finest):
        smooth = sitk.SmoothingRecursiveGaussian(lumen, sigma) * (sigma * sigma)
        obj = sitk.ObjectnessMeasure(smooth, alpha=ALPHA, beta=BETA, gamma=GAMMA_HU, scaleObjectnessMeasure=False,
                                     objectDimension=1, brightObject=True)
        best = obj if best is None else sitk.Maximum(best, obj)
    return best


def _shrunk(image: sitk.Image, spacing_mm: float) -> sitk.Image:
    """``image`` block-averaged to voxels of about ``spacing_mm`` (itself where it is not finer)."""
    factors = [max(1, round(spacing_mm / s)) for s in image.GetSpacing()]
    return sitk.BinShrink(image, factors) if max(factors) > 1 else image


def _radius_vox(radius_mm: float, spacing_mm) -> list[int]:
    return [max(1, int(round(radius_mm / s))) for s in spacing_mm]


def _components(mask: np.ndarray, reference: sitk.Image, min_mm3: float) -> np.ndarray:
    """26-connected components of ``mask`` of at least ``min_mm3``, labelled 1.. by size (int array)."""
    image = sitk.GetImageFromArray(mask.astype(np.uint8))
    image.CopyInformation(reference)
    min_voxels = int(np.ceil(min_mm3 / float(np.prod(reference.GetSpacing()))))
    return sitk.GetArrayFromImage(sitk.RelabelComponent(sitk.ConnectedComponent(image, True), minimumObjectSize=min_voxels))


def _long(cc: np.ndarray, reference: sitk.Image, span_mm: float) -> list[int]:
    """Labels of the components of ``cc`` that span at least ``span_mm`` along the array's slowest axis."""
    k = np.nonzero(cc)[0]
    labels = cc[cc > 0]
    if labels.size == 0:
        return []
    n = int(cc.max()) + 1
    lo = np.full(n, np.iinfo(np.int64).max)
    hi = np.full(n, -1)
    np.minimum.at(lo, labels, k)
    np.maximum.at(hi, labels, k)
    step = reference.GetSpacing()[2]
    return [int(v) for v in np.flatnonzero((hi - lo + 1) * step >= span_mm) if v > 0]


def _trees(hu: sitk.Image) -> tuple[sitk.Image, list[dict]]:
    """The kept trees (uint8 mask on ``hu``'s grid) and every candidate tree's numbers."""
    lumen = sitk.GetImageFromArray(lumen_image(sitk.GetArrayViewFromImage(hu)))
    lumen.CopyInformation(hu)
    tube = sitk.GetArrayFromImage(tubularity(lumen))
    a = sitk.GetArrayViewFromImage(hu)
    cortex = sitk.GetImageFromArray((a > CORTEX_HU).astype(np.uint8))
    cortex.CopyInformation(hu)
    solid_bone = sitk.BinaryFillhole(cortex, fullyConnected=False)
    inside_bone = sitk.GetArrayViewFromImage(solid_bone) > 0
    bone = sitk.GetImageFromArray((a > BONE_HU).astype(np.uint8))
    bone.CopyInformation(hu)
    near_bone = sitk.GetArrayViewFromImage(sitk.BinaryDilate(bone, _radius_vox(BONE_MARGIN_MM, hu.GetSpacing()), sitk.sitkBall)) > 0
    bright = sitk.GetImageFromArray(((a >= LUMEN_HU[0]) & ~inside_bone).astype(np.uint8))
    bright.CopyInformation(hu)
    thick = sitk.BinaryDilate(sitk.BinaryMorphologicalOpening(bright, _radius_vox(THICK_MM, hu.GetSpacing()), sitk.sitkBall), [1, 1, 1])
    in_range = (a >= LUMEN_HU[0]) & (a <= LUMEN_HU[1]) & ~inside_bone & (sitk.GetArrayViewFromImage(thick) == 0)
    candidate = in_range & (tube > np.where(near_bone, OBJECTNESS_NEAR_BONE, OBJECTNESS_LOW))
    seed_cc = _components(in_range & ~near_bone & (tube > OBJECTNESS_SEED), hu, MIN_SEED_MM3)
    seeds = np.isin(seed_cc, _long(seed_cc, hu, SEED_SPAN_MM))
    cc = _components(candidate | seeds, hu, MIN_TREE_MM3)
    voxel_mm3 = float(np.prod(hu.GetSpacing()))
    trees = []
    flat, values, seeded = cc.ravel(), a.ravel(), seeds.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, int(cc.max()) + 2))
    for n in range(1, int(cc.max()) + 1):
        idx = order[bounds[n - 1]:bounds[n]]
        trees.append({"label": n, "volume_mm3": len(idx) * voxel_mm3, "seed_mm3": float(seeded[idx].sum() * voxel_mm3),
                      "lumen_hu": float(np.percentile(values[idx], TREE_HU_PERCENTILE))})
    kept = [t["label"] for t in trees if t["seed_mm3"] > 0]
    for t in trees:
        t["kept"] = t["label"] in kept
    mask = sitk.GetImageFromArray(np.isin(cc, kept).astype(np.uint8))
    mask.CopyInformation(hu)
    return mask, trees


def _lumen(hu: sitk.Image, trees: sitk.Image) -> sitk.Image:
    """Half-maximum lumen (uint8 on ``hu``'s grid) around the ``trees`` (any grid)."""
    trees = sitk.Resample(trees, hu, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    radius = _radius_vox(GROW_MM, hu.GetSpacing())
    peak = sitk.GrayscaleDilate(sitk.Mask(hu, trees, outsideValue=-1024.0), radius, sitk.sitkBall)
    near = sitk.BinaryDilate(trees, radius, sitk.sitkBall)
    a, p = sitk.GetArrayViewFromImage(hu), sitk.GetArrayViewFromImage(peak)
    lumen = (sitk.GetArrayViewFromImage(near) > 0) & (a >= np.maximum(0.5 * (p + SOFT_TISSUE_HU), LUMEN_HU[0])) & (a < BONE_HU)
    out = sitk.GetImageFromArray(lumen.astype(np.uint8))
    out.CopyInformation(hu)
    return out


def artery_mask_from_cta(volume: Volume) -> Volume:
    """Contrast-filled arteries of a CTA (HU) as a uint8 {0, 1} mask on its grid (module docstring).

    ``metadata``: ``method``, ``contrast`` (False when no tree was found: the mask is empty),
    ``trees`` (each candidate tree's ``volume_mm3``, ``lumen_hu`` and whether it was ``kept``)."""
    full = sitk.Cast(sitk_from_volume(volume), sitk.sitkFloat32)
    tube_grid = _shrunk(full, TUBE_SPACING_MM)
    trees, numbers = _trees(tube_grid)
    found = any(t["kept"] for t in numbers)
    method = (f"Frangi tubularity (sitk.ObjectnessMeasure, scales {', '.join(f'{s:g}' for s in SCALES_MM)} mm) on a "
              f"{TUBE_SPACING_MM:g} mm grid, large bright trees, half-maximum lumen on a {LUMEN_SPACING_MM:g} mm grid")
    if not found:
        return volume.like(np.zeros(volume.array.shape, np.uint8), kind="vessel_mask", contrast=False, trees=numbers,
                           method=method + ": no contrast-filled tree found (CT without contrast?), empty")
    lumen_grid = _shrunk(full, LUMEN_SPACING_MM)
    lumen = _lumen(lumen_grid, trees)
    if lumen_grid is not full:
        lumen = sitk.Resample(lumen, full, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    return volume.like(sitk.GetArrayFromImage(lumen).astype(np.uint8), kind="vessel_mask", contrast=True, trees=numbers,
                       method=method)
