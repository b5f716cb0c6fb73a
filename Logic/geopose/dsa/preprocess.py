"""DSA preprocessing (docs/conventions.md section 5), one function per step.

``preprocess_dsa`` chains them: attenuation-like frames (absorbers bright, see
:meth:`DSARun.attenuation`) -> MAP (max over frames) -> cranium mask -> intensity
clipping -> resampling to the model geometry -> masking -> bilateral filter -> min-max.
The same chain at the acquisition SDD (downsampled) gives the TTO target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from .. import contract as C
from ..geometry.detector import Detector
from ..errors import InputError
from ..images import block_mean, blur_and_sample_grid, disc_filter, normalize_minmax, wide_gaussian_blur
from ..options import check_clip_percentiles
from .run import DSARun

__all__ = [
    "PreparedDSA",
    "temporal_map",
    "dsa_cranium_mask",
    "clip_intensities",
    "resample_to_detector",
    "resample_to_model_sdd",
    "bilateral",
    "minmax",
    "intensity_unit",
    "preprocess_dsa",
    "vessel_image",
    "bolus_weighted_mean",
    "early_frames_mean",
    "TTO_TARGET_PX",
]

#: Default size (px, along the longer image side) of the TTO target at the acquisition SDD.
TTO_TARGET_PX = 256
#: The bilateral range sigma is in units of an 8-bit image (see :func:`intensity_unit`).
REFERENCE_LEVELS = 255.0
#: The DSA cranium mask is computed on the MAP block-averaged to at most this many pixels per side.
MASK_WORK_PX = 256
#: Radius of the grey-scale opening that removes opacified vessels from the MAP before the cranium
#: mask's threshold, as a fraction of the image's longer side (16 px of the 256-px work grid, about
#: 19 mm on a 300 mm detector): wider than the neck's carotids, far narrower than the head.
VESSEL_OPENING_FRACTION = 1.0 / 16.0
#: Before the threshold the opened MAP is clipped at this percentile over the exposed field, so that a
#: bright opacified region wider than the opening (an AVM nidus, a filled sinus) joins the head's class.
MASK_CLIP_PERCENTILE = 90.0
#: The bolus curve of the vessel image is read from each frame less its Gaussian blur of this sd (mm on the
#: detector): vessels (a carotid is about 8 mm wide there) stay, the capillary blush (as wide as the cranium)
#: goes. Chosen on validation seeds 6013-6027 among 2.5, 5 and 10 mm (experiments/vessel_image/vessel_image.md).
BOLUS_DETAIL_SIGMA_MM = 10.0
#: Each frame's noise level (the sd of its fine detail over the cranium) is measured on every this-many-th pixel
#: along rows and columns (a 1024^2 run: 256^2 samples per frame).
NOISE_LEVEL_STRIDE = 4
#: Empty cells around the bilateral grid (its blur reaches two cells).
_GRID_PAD = 2


def temporal_map(frames: np.ndarray) -> np.ndarray:
    """Maximum intensity over time: ``(T, H, W)`` -> ``(H, W)`` float32."""
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] < 1:
        raise InputError(f"temporal_map needs (T, H, W) frames, got shape {frames.shape}")
    return frames.max(axis=0).astype(np.float32)


def _largest_component_filled(mask: np.ndarray) -> np.ndarray:
    image = sitk.GetImageFromArray(mask.astype(np.uint8))
    cc = sitk.RelabelComponent(sitk.ConnectedComponent(image, True), sortByObjectSize=True)
    filled = sitk.BinaryFillhole(sitk.Cast(cc == 1, sitk.sitkUInt8), fullyConnected=False)
    return sitk.GetArrayFromImage(filled).astype(np.uint8)


def _opening_within(image: np.ndarray, domain: np.ndarray, radius_px: int) -> np.ndarray:
    """Grey-scale opening (erosion, then dilation, disc of ``radius_px``) of ``image`` restricted to
    ``domain``: pixels outside it take no part (they count as the image's maximum in the erosion and
    its minimum in the dilation), so the shutters do not erode the head next to them."""
    inside = image[domain]
    eroded = disc_filter(np.where(domain, image, inside.max()), radius_px, erode=True)
    return disc_filter(np.where(domain, eroded, inside.min()), radius_px, erode=False)


def dsa_cranium_mask(image: np.ndarray) -> np.ndarray:
    """Head (cranium) mask of an attenuation-like MAP ``(H, W)`` as uint8 {0, 1}.

    Method, on the MAP block-averaged to at most ``MASK_WORK_PX`` pixels per side: the exposed
    field is where the MAP is above its minimum (the shutters hold the minimum); the opacified
    vessels are removed by a grey-scale opening within that field with a disc of
    ``VESSEL_OPENING_FRACTION`` of the longer side (vessels are narrower than the disc, the head is
    not; what is left is the head's noise-drawn level, experiments/cranium_masks/cranium_masks.md); Otsu threshold over
    the exposed field, the largest 8-connected component, holes filled; repeated back to the full
    matrix (the mask is resampled to the 256-px model geometry afterwards). Without the opening a
    densely opacified run's vessels take Otsu's bright class and the mask is the vessel tree.
    Raises when the image is constant.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise InputError(f"dsa_cranium_mask needs a 2D MAP, got shape {image.shape}")
    if image.max() <= image.min():
        raise InputError("the MAP is constant: no head to mask; check the run or supply a mask")
    shape = image.shape
    f = max(1, int(np.ceil(max(shape) / MASK_WORK_PX)))
    exposed = image > image.min()
    if f > 1:
        image, exposed = block_mean(image, (f, f)), block_mean(exposed.astype(np.float32), (f, f)) > 0.5
    radius_px = max(1, round(VESSEL_OPENING_FRACTION * max(image.shape)))
    opened = _opening_within(image, exposed, radius_px)
    opened = np.minimum(opened, np.percentile(opened[exposed], MASK_CLIP_PERCENTILE))
    otsu = sitk.OtsuThresholdImageFilter()
    otsu.Execute(sitk.GetImageFromArray(opened[exposed][None]))
    mask = _largest_component_filled((opened > otsu.GetThreshold()) & exposed)
    if f > 1:
        mask = np.repeat(np.repeat(mask, f, axis=0), f, axis=1)[: shape[0], : shape[1]]
    return np.ascontiguousarray(mask)


def clip_intensities(
    image: np.ndarray, support: np.ndarray | None = None, percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES
) -> np.ndarray:
    """Clip to the 25th..75th percentile over the non-empty columns, then subtract the minimum.

    Interpretation of docs/conventions.md 5: a column is *non-empty* when it holds at least one
    pixel of ``support`` (the cranium mask; default: pixels that are not 0). The
    percentiles are taken over all pixels of those columns (so image columns entirely
    outside the head, e.g. collimated borders, do not bias them); the whole image is
    clipped to that range and shifted so its minimum is 0. Anything brighter than the
    75th percentile (vessels, skull rim) saturates: the result is the head *silhouette*
    the paper describes, not a vessel image.
    """
    percentiles = check_clip_percentiles(percentiles)
    image = np.asarray(image, dtype=np.float32)
    support = image != 0 if support is None else np.asarray(support) > 0
    if support.shape != image.shape:
        raise InputError(f"support mask {support.shape} does not match the image {image.shape}")
    columns = support.any(axis=0)
    if not columns.any():
        raise InputError("no non-empty column to take intensity percentiles from: the mask is empty")
    lo, hi = np.percentile(image[:, columns], percentiles)
    clipped = np.clip(image, lo, hi)
    return clipped - clipped.min()


def resample_to_detector(image: np.ndarray, source: Detector, target: Detector) -> np.ndarray:
    """Resample a detector image to another detector sharing the same source and axis.

    Each target pixel centre is projected from the source onto the ``source`` detector
    plane (scale ``source.sdd / target.sdd``, principal offsets and the reversed column
    axis honoured through ``Detector.pixel_to_camera`` / ``camera_to_pixel``) and the
    image is sampled there bilinearly; outside the image the value is 0 (padding). When
    a target pixel covers several source pixels the image is Gaussian-smoothed first
    (sigma = 0.5 x the ratio) against aliasing. This is the "centre crop/pad with the focal
    ratio, then resize" of docs/conventions.md 5, done exactly.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.shape != source.shape:
        raise InputError(f"image {image.shape} does not match the source detector {source.shape}")
    # A target pixel's source row depends on its row alone, its column on its column (same axes): sample a grid.
    src_rows = source.camera_to_pixel(target.pixel_to_camera(np.stack((np.arange(target.rows, dtype=np.float64),
                                                                       np.zeros(target.rows)), axis=-1)))[:, 0]
    src_cols = source.camera_to_pixel(target.pixel_to_camera(np.stack((np.zeros(target.cols),
                                                                       np.arange(target.cols, dtype=np.float64)), axis=-1)))[:, 1]
    ratio = (  # target pixel size projected onto the source plane, in source pixels
        target.spacing_mm[0] * source.sdd_mm / (target.sdd_mm * source.spacing_mm[0]),
        target.spacing_mm[1] * source.sdd_mm / (target.sdd_mm * source.spacing_mm[1]),
    )
    sigma_px = tuple(0.5 * r if r > 1 else 0.0 for r in ratio)
    return blur_and_sample_grid(image, src_rows, src_cols, sigma_px).astype(np.float32)


def resample_to_model_sdd(image: np.ndarray, detector: Detector, model: Detector | None = None) -> np.ndarray:
    """Image at the acquisition geometry ``detector`` -> the model geometry (256 x 256,
    1.2 mm, SDD 1020 mm by default), same source and central ray."""
    return resample_to_detector(image, detector, model or Detector.model())


def intensity_unit(run: DSARun) -> float:
    """Stored-value step that corresponds to one level of an 8-bit image.

    The range sigma (11) of docs/conventions.md 5 is in 8-bit units, the published DSA being
    8-bit: for a run with ``bits_stored`` b the unit is ``(2**b - 1) / 255``; without
    that information (NIfTI input) the run's value span / 255.
    """
    bits = int(run.metadata.get("bits_stored", 0) or 0)
    if bits > 0:
        return (2.0**bits - 1.0) / REFERENCE_LEVELS
    span = float(run.frames.max() - run.frames.min())
    return span / REFERENCE_LEVELS if span > 0 else 1.0


def bilateral(
    image: np.ndarray,
    spatial_sigma_px: float = C.BILATERAL_SPATIAL_SIGMA_PX,
    range_sigma: float = C.BILATERAL_RANGE_SIGMA,
) -> np.ndarray:
    """Edge-preserving bilateral filter, spatial sigma in pixels, range sigma in image intensity
    units, as a bilateral grid (Paris and Durand 2006): the image is splatted (trilinearly) onto
    a grid of one cell per sigma in space and range, the grid is blurred with a unit Gaussian,
    and sliced back at every pixel. Within a few per cent of the brute-force filter, at a
    thousandth of its cost for the 11-px sigma of docs/conventions.md 5."""
    x = np.asarray(image, dtype=np.float64)
    if x.ndim != 2:
        raise InputError(f"bilateral needs a 2D image, got shape {x.shape}")
    lo = float(x.min())
    rows, cols = np.mgrid[: x.shape[0], : x.shape[1]]
    coords = [rows / spatial_sigma_px + _GRID_PAD, cols / spatial_sigma_px + _GRID_PAD, (x - lo) / range_sigma + _GRID_PAD]
    shape = tuple(int(np.ceil(c.max())) + _GRID_PAD + 1 for c in coords)
    base = [np.floor(c).astype(np.int64) for c in coords]
    frac = [c - b for c, b in zip(coords, base)]
    strides = (shape[1] * shape[2], shape[2], 1)
    grid = np.zeros((2, int(np.prod(shape))))
    corners = []
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                w = (frac[0] if dz else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1]) * (frac[2] if dx else 1 - frac[2])
                idx = (base[0] + dz) * strides[0] + (base[1] + dy) * strides[1] + (base[2] + dx)
                corners.append((idx.ravel(), w.ravel()))
                grid[0] += np.bincount(idx.ravel(), weights=(w * x).ravel(), minlength=grid.shape[1])
                grid[1] += np.bincount(idx.ravel(), weights=w.ravel(), minlength=grid.shape[1])
    grid = grid.reshape(2, *shape)
    kernel = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0  # binomial, sd 1 cell
    for axis in (1, 2, 3):
        grid = sum(w * np.roll(grid, k - 2, axis=axis) for k, w in enumerate(kernel))
    flat = grid.reshape(2, -1)
    num = sum(flat[0][idx] * w for idx, w in corners)
    den = sum(flat[1][idx] * w for idx, w in corners)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), x.ravel()).reshape(x.shape).astype(np.float32)


def minmax(image: np.ndarray) -> np.ndarray:
    """Min-max to [0, 1] through the networks' :func:`geopose.nets.normalize_minmax`."""
    return normalize_minmax(np.asarray(image, dtype=np.float32)[None, None])[0, 0]


@dataclass
class PreparedDSA:
    """A preprocessed DSA view.

    ``map`` / ``mask``: native-resolution attenuation-like MAP and its cranium mask.
    ``model_image`` / ``model_mask`` on ``model_detector`` (256 x 256, 1.2 mm, SDD 1020):
    the Init/Refine target. ``tto_image`` / ``tto_mask`` on ``tto_detector`` (the
    acquisition SDD, downsampled): the test-time-optimisation target; ``tto_vessels`` the
    run's opacified vessels on the same detector (:func:`vessel_image`), and ``tto_vessels_early`` the same of the
    run's first half (:func:`early_frames_mean`; None: not made), which ``register/vessel_image.py`` may use instead.
    """

    map: np.ndarray
    mask: np.ndarray
    model_image: np.ndarray
    model_mask: np.ndarray
    model_detector: Detector
    tto_image: np.ndarray
    tto_mask: np.ndarray
    tto_detector: Detector
    tto_vessels: np.ndarray
    view_role: str
    view_label: int
    tto_vessels_early: np.ndarray | None = None


def bolus_weighted_mean(frames: np.ndarray, mask: np.ndarray, pixel_mm: tuple[float, float]) -> np.ndarray:
    """The frames ``(T, H, W)`` averaged with weights that follow the run's own bolus (a temporal
    matched filter). The curve is read from the frames' fine detail (each frame less its Gaussian blur of
    ``BOLUS_DETAIL_SIGMA_MM``; ``pixel_mm`` the frames' pixel size (rows, columns), mm) at the pixels
    where its temporal mean reaches ``BOLUS_PIXEL_PERCENTILE`` over the cranium ``mask`` (the brightest
    vessels); the weights are that curve less its median over frames, negative parts zeroed. Fine detail
    leaves out the capillary blush, a haze as wide as the cranium that follows the arteries and outlasts
    them: read from the plain frames the curve followed the blush in short runs and weighted the late
    frames, whose vessels are gone (experiments/vessel_image/vessel_image.md). The curve is divided by each
    frame's noise variance (:func:`frame_noise_levels`), the matched filter's weight where the noise changes from
    frame to frame: subtraction residue from patient motion grows over a run, lines the skull's edges (which then
    rank among the bright pixels) and, unweighted, made the curve rise to the run's last frames
    (experiments/vessel_image/residue.md). Frames without contrast get no weight, so the noise they add to a plain
    mean drops out; a run without a bolus (flat curve, or one frame) gets the plain mean. float32 ``(H, W)``."""
    frames = np.asarray(frames, dtype=np.float32)
    inside = np.asarray(mask) > 0
    mean = frames.mean(axis=0)
    if not inside.any():
        raise InputError("the cranium mask is empty: no pixels to read the bolus from")
    sigma_px = tuple(BOLUS_DETAIL_SIGMA_MM / float(s) for s in pixel_mm)
    detail = mean - wide_gaussian_blur(mean, sigma_px)
    bright = (inside & (detail >= np.percentile(detail[inside], C.BOLUS_PIXEL_PERCENTILE))).astype(np.float64)
    # each frame's detail averaged over the bright pixels, as one kernel (the blur is linear and symmetric)
    kernel = (bright - wide_gaussian_blur(bright, sigma_px)) / bright.sum()
    curve = np.tensordot(frames, kernel.astype(np.float32), axes=2).astype(np.float64)
    curve = curve / np.maximum(frame_noise_levels(frames, inside & ~(bright > 0), sigma_px), 1e-12) ** 2
    weights = np.clip(curve - np.median(curve), 0.0, None)
    if not weights.sum() > 0:
        return mean
    return np.tensordot((weights / weights.sum()).astype(np.float32), frames, axes=1)


def early_frames_mean(frames: np.ndarray) -> np.ndarray:
    """The mean of a run's first half of frames ``(T, H, W)`` (the middle frame included when ``T`` is odd), float32
    ``(H, W)``: the arteries fill before the capillary blush and the veins, so this shows them where the bolus curve
    (:func:`bolus_weighted_mean`) followed the late frames (experiments/vessel_image/candidates.md)."""
    frames = np.asarray(frames, dtype=np.float32)
    return frames[: max(1, (len(frames) + 1) // 2)].mean(axis=0)


def frame_noise_levels(frames: np.ndarray, inside: np.ndarray, sigma_px: tuple[float, float]) -> np.ndarray:
    """Per frame ``(T,)`` the sd of its fine detail (the frame less its Gaussian blur of ``sigma_px`` (rows,
    columns), pixels) over the cranium ``inside`` (bool ``(H, W)``), sampled on every :data:`NOISE_LEVEL_STRIDE`-th
    pixel (every pixel where that leaves fewer than 16 of the cranium): quantum noise and motion residue
    (:func:`bolus_weighted_mean` leaves its brightest pixels, vessels and residue fringe, out of ``inside``). Ones
    where ``inside`` has fewer than 2 pixels (no level to read)."""
    step = NOISE_LEVEL_STRIDE if np.count_nonzero(inside[::NOISE_LEVEL_STRIDE, ::NOISE_LEVEL_STRIDE]) >= 16 else 1
    sampled, where = frames[:, ::step, ::step], inside[::step, ::step]
    if np.count_nonzero(where) < 2:
        return np.ones(len(frames))
    sigma = tuple(s / step for s in sigma_px)
    return np.array([(f - wide_gaussian_blur(f, sigma))[where].std() for f in sampled], dtype=np.float64)


def vessel_image(image: np.ndarray, mask: np.ndarray, source: Detector, target: Detector) -> np.ndarray:
    """The opacified vessels of a run's bolus-weighted mean ``(H, W)`` (:func:`bolus_weighted_mean`)
    on ``target``: clipped to its ``VESSEL_CLIP_PERCENTILES`` over the cranium ``mask`` (below:
    noise; above: a few saturated pixels), masked, resampled (anti-aliased), min-max. Subtraction
    noise has zero mean, so averaging over frames keeps the vessels and drops the noise-made head
    silhouette (and the bright skull base) that the MAP's maximum holds; this is what the TTO aligns
    the CTA's vessels on (experiments/tto_objective/objective.md). What noise is left moves the objective's optimum
    (experiments/tto_objective/objective_real_heads.md): weighting the frames by the bolus leaves less of it than the
    plain mean."""
    inside = np.asarray(mask) > 0
    lo, hi = np.percentile(image[inside], C.VESSEL_CLIP_PERCENTILES)
    vessels = (np.clip(image, lo, hi) - lo) * inside
    return minmax(resample_to_detector(vessels.astype(np.float32), source, target))


def _finish(clipped: np.ndarray, mask: np.ndarray, source: Detector, target: Detector, unit: float) -> tuple[np.ndarray, np.ndarray]:
    image = resample_to_detector(clipped, source, target)
    m = (resample_to_detector(mask.astype(np.float32), source, target) > 0.5).astype(np.uint8)
    image = image * m
    image = bilateral(image / unit, C.BILATERAL_SPATIAL_SIGMA_PX, C.BILATERAL_RANGE_SIGMA)
    return minmax(image), m


def preprocess_dsa(
    run: DSARun,
    *,
    mask: np.ndarray | None = None,
    invert: bool | None = None,
    tto_px: int = TTO_TARGET_PX,
    model_clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES,
) -> PreparedDSA:
    """docs/conventions.md 5 on one run: MAP, cranium mask (``mask`` overrides; native size),
    clipping, resampling, masking, bilateral (on the 8-bit scale, :func:`intensity_unit`)
    and min-max, for the model geometry and for the TTO geometry (acquisition SDD,
    ``tto_px`` pixels along the longer side). ``invert`` as in :meth:`DSARun.attenuation`.
    ``model_clip_percentiles`` changes the clip of the networks' image only (the TTO
    target keeps docs/conventions.md 5); see ``experiments/init_depth/init_depth.md``.
    """
    frames = run.attenuation(invert)
    image = temporal_map(frames)
    if mask is None:
        mask = dsa_cranium_mask(image)
    else:
        mask = (np.asarray(mask) > 0).astype(np.uint8)
        if mask.shape != image.shape:
            raise InputError(f"the given mask is {mask.shape} but the run's frames are {image.shape}")
        if not mask.any():
            raise InputError("the given mask is empty: supply a mask of the head or let the run's MAP define it")
    clipped = clip_intensities(image, mask)
    unit = intensity_unit(run)
    model = Detector.model()
    same = check_clip_percentiles(model_clip_percentiles) == C.MAP_CLIP_PERCENTILES
    model_clipped = clipped if same else clip_intensities(image, mask, model_clip_percentiles)
    model_image, model_mask = _finish(model_clipped, mask, run.detector, model, unit)
    h, w = run.detector.shape
    scale = tto_px / max(h, w)
    tto = run.detector.resized(max(1, round(h * scale)), max(1, round(w * scale)))
    tto_image, tto_mask = _finish(clipped, mask, run.detector, tto, unit)
    tto_vessels = vessel_image(bolus_weighted_mean(frames, mask, run.detector.spacing_mm), mask, run.detector, tto)
    tto_vessels_early = vessel_image(early_frames_mean(frames), mask, run.detector, tto)
    return PreparedDSA(image, mask, model_image, model_mask, model, tto_image, tto_mask, tto, tto_vessels, run.view_role,
                       run.view_label, tto_vessels_early)
