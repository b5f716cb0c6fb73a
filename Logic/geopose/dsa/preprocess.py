"""DSA preprocessing (CONVENTIONS section 5), one function per step.

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
from ..nets.preprocess import normalize_minmax
from ..options import check_clip_percentiles
from ..errors import InputError
from .run import DSARun

__all__ = [
    "PreparedDSA",
    "check_clip_percentiles",
    "temporal_map",
    "dsa_cranium_mask",
    "clip_intensities",
    "resample_to_detector",
    "resample_to_model_sdd",
    "bilateral",
    "minmax",
    "intensity_unit",
    "preprocess_dsa",
    "TTO_TARGET_PX",
]

#: Default size (px, along the longer image side) of the TTO target at the acquisition SDD.
TTO_TARGET_PX = 256
#: The bilateral range sigma is in units of an 8-bit image (see :func:`intensity_unit`).
REFERENCE_LEVELS = 255.0


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


def dsa_cranium_mask(image: np.ndarray) -> np.ndarray:
    """Head (cranium) mask of an attenuation-like MAP ``(H, W)`` as uint8 {0, 1}.

    Method: Otsu threshold (head brighter than the air around it), the largest
    8-connected component, holes filled. Raises when the image is constant.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise InputError(f"dsa_cranium_mask needs a 2D MAP, got shape {image.shape}")
    if image.max() <= image.min():
        raise InputError("the MAP is constant: no head to mask; check the run or supply a mask")
    otsu = sitk.OtsuThreshold(sitk.GetImageFromArray(image), 0, 1)
    return _largest_component_filled(sitk.GetArrayFromImage(otsu) > 0)


def clip_intensities(
    image: np.ndarray, support: np.ndarray | None = None, percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES
) -> np.ndarray:
    """Clip to the 25th..75th percentile over the non-empty columns, then subtract the minimum.

    Interpretation of CONVENTIONS 5: a column is *non-empty* when it holds at least one
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


def _gaussian_blur(image: np.ndarray, sigma_px: tuple[float, float]) -> np.ndarray:
    """Separable Gaussian (radius ``ceil(3 sigma)``, edge values repeated) along rows then columns."""
    for axis, sigma in enumerate(sigma_px):
        if sigma <= 0:
            continue
        radius = max(1, int(np.ceil(3 * sigma)))
        k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
        k /= k.sum()
        pad = [(0, 0), (0, 0)]
        pad[axis] = (radius, radius)
        padded = np.pad(image, pad, mode="edge")
        n = image.shape[axis]
        image = sum(w * np.take(padded, np.arange(i, i + n), axis=axis) for i, w in enumerate(k))
    return image


def _bilinear(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at fractional pixel ``(rows, cols)``; outside the image it is 0."""
    h, w = image.shape
    r0, c0 = np.floor(rows), np.floor(cols)
    fr, fc = rows - r0, cols - c0
    r0, c0 = r0.astype(np.int64), c0.astype(np.int64)
    out = np.zeros(rows.shape, dtype=np.float64)
    for dr, wr in ((0, 1.0 - fr), (1, fr)):
        for dc, wc in ((0, 1.0 - fc), (1, fc)):
            r, c = r0 + dr, c0 + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            out += np.where(inside, image[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], 0.0) * wr * wc
    return out


def resample_to_detector(image: np.ndarray, source: Detector, target: Detector) -> np.ndarray:
    """Resample a detector image to another detector sharing the same source and axis.

    Each target pixel centre is projected from the source onto the ``source`` detector
    plane (scale ``source.sdd / target.sdd``, principal offsets and the reversed column
    axis honoured through ``Detector.pixel_to_camera`` / ``camera_to_pixel``) and the
    image is sampled there bilinearly; outside the image the value is 0 (padding). When
    a target pixel covers several source pixels the image is Gaussian-smoothed first
    (sigma = 0.5 x the ratio) against aliasing. This is the "centre crop/pad with the focal
    ratio, then resize" of CONVENTIONS 5, done exactly.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.shape != source.shape:
        raise InputError(f"image {image.shape} does not match the source detector {source.shape}")
    src_rc = source.camera_to_pixel(target.camera_points())
    ratio = (  # target pixel size projected onto the source plane, in source pixels
        target.spacing_mm[0] * source.sdd_mm / (target.sdd_mm * source.spacing_mm[0]),
        target.spacing_mm[1] * source.sdd_mm / (target.sdd_mm * source.spacing_mm[1]),
    )
    smooth = _gaussian_blur(image.astype(np.float64), tuple(0.5 * r if r > 1 else 0.0 for r in ratio))
    return _bilinear(smooth, src_rc[..., 0], src_rc[..., 1]).astype(np.float32)


def resample_to_model_sdd(image: np.ndarray, detector: Detector, model: Detector | None = None) -> np.ndarray:
    """Image at the acquisition geometry ``detector`` -> the model geometry (256 x 256,
    1.2 mm, SDD 1020 mm by default), same source and central ray."""
    return resample_to_detector(image, detector, model or Detector.model())


def intensity_unit(run: DSARun) -> float:
    """Stored-value step that corresponds to one level of an 8-bit image.

    The range sigma (11) of CONVENTIONS 5 is in 8-bit units, the published DSA being
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
    """Edge-preserving bilateral filter (SimpleITK), spatial sigma in pixels, range sigma
    in image intensity units."""
    img = sitk.GetImageFromArray(np.asarray(image, dtype=np.float32))
    out = sitk.Bilateral(img, domainSigma=float(spatial_sigma_px), rangeSigma=float(range_sigma))
    return sitk.GetArrayFromImage(out).astype(np.float32)


def minmax(image: np.ndarray) -> np.ndarray:
    """Min-max to [0, 1] through the networks' :func:`geopose.nets.normalize_minmax`."""
    return normalize_minmax(np.asarray(image, dtype=np.float32)[None, None])[0, 0]


@dataclass
class PreparedDSA:
    """A preprocessed DSA view.

    ``map`` / ``mask``: native-resolution attenuation-like MAP and its cranium mask.
    ``model_image`` / ``model_mask`` on ``model_detector`` (256 x 256, 1.2 mm, SDD 1020):
    the Init/Refine target. ``tto_image`` / ``tto_mask`` on ``tto_detector`` (the
    acquisition SDD, downsampled): the test-time-optimisation target.
    """

    map: np.ndarray
    mask: np.ndarray
    model_image: np.ndarray
    model_mask: np.ndarray
    model_detector: Detector
    tto_image: np.ndarray
    tto_mask: np.ndarray
    tto_detector: Detector
    view_role: str
    view_label: int


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
    """CONVENTIONS 5 on one run: MAP, cranium mask (``mask`` overrides; native size),
    clipping, resampling, masking, bilateral (on the 8-bit scale, :func:`intensity_unit`)
    and min-max, for the model geometry and for the TTO geometry (acquisition SDD,
    ``tto_px`` pixels along the longer side). ``invert`` as in :meth:`DSARun.attenuation`.
    ``model_clip_percentiles`` changes the clip of the networks' image only (the TTO
    target keeps CONVENTIONS 5); see ``docs/init_depth.md``.
    """
    image = temporal_map(run.attenuation(invert))
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
    return PreparedDSA(image, mask, model_image, model_mask, model, tto_image, tto_mask, tto, run.view_role, run.view_label)
