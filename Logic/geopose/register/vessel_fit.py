"""Which of the vessel voxels the opacified read kept the runs' vessel images need: a two-view emission fit (numpy).

The opacified read (``opacified.py``) keeps a CTA vessel voxel wherever every view's vessel image shows contrast where
it projects, with a tolerance for a pose a few mm off. A vein that wraps an artery passes it, and so does one that
lies beside an artery: both project onto the artery's image in both views (the cavernous sinus round the ICA; the
jugular veins by the carotids). The fit asks instead which voxels the images *need*. Each voxel gets a weight
w >= 0, fitted by MLEM (the EM algorithm of emission tomography) so that the voxels' projections reproduce every
view's vessel image; the projections are bilinear splats blurred by :data:`FIT_BLUR_PX`. A vein that wraps an artery
projects outside the artery's lumen in at least one view. There the artery alone explains the image, and the vein's
weight falls. Evidence (experiments/vessel_mask/selection_fit.md):
- Read at the true pose on validation phantom 6020, the fit keeps 420 of 482 artery voxels and 60 of 310 vein voxels.
- The TTO started at the truth then drifts 0.47 mm, against 0.73 mm (6020-6028).
- The fit keeps what explains the images *at the pose it is read at*. So it judges a pose well, but cannot steer a
  search: read at the networks' estimate it held the pose there (carotid mPCD 1.73 -> 2.31 mm on validation).
"""

from __future__ import annotations

from typing import Final, Sequence

import numpy as np

from ..images import gaussian_blur

__all__ = ["FIT_BLUR_PX", "FIT_SHARE", "FIT_ITERATIONS", "explaining_weights", "explaining"]

#: Blur (sd, px at the TTO size) of a voxel's splat: its footprint and the image's own blur.
FIT_BLUR_PX: Final = 0.7
#: A voxel is kept when its weight reaches this share of the weights' 90th percentile.
FIT_SHARE: Final = 0.05
#: MLEM iterations (a few milliseconds for a thousand voxels).
FIT_ITERATIONS: Final = 30


def _splats(pixels: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices and bilinear weights ``(N, 4)`` of each point at ``pixels`` ``(N, 2)`` (row, col); a corner
    outside the image has weight 0."""
    h, w = shape
    r0, c0 = np.floor(pixels[:, 0]), np.floor(pixels[:, 1])
    fr, fc = pixels[:, 0] - r0, pixels[:, 1] - c0
    index, weight = [], []
    for dr, wr in ((0, 1.0 - fr), (1, fr)):
        for dc, wc in ((0, 1.0 - fc), (1, fc)):
            r, c = r0.astype(np.int64) + dr, c0.astype(np.int64) + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            index.append(np.where(inside, np.clip(r, 0, h - 1) * w + np.clip(c, 0, w - 1), 0))
            weight.append(np.where(inside, wr * wc, 0.0))
    return np.stack(index, axis=1), np.stack(weight, axis=1)


def explaining_weights(pixels: Sequence[np.ndarray], images: Sequence[np.ndarray], blur_px: float = FIT_BLUR_PX,
                       iterations: int = FIT_ITERATIONS) -> np.ndarray:
    """Per voxel, its MLEM weight ``(N,)`` explaining every view's vessel image ``images[v]`` ``(h, w)`` (negative
    values count as 0), the voxel projecting at ``pixels[v]`` ``(N, 2)`` (row, col) in that view. The weights'
    scale is arbitrary."""
    blur = lambda image: gaussian_blur(image, (blur_px, blur_px))  # noqa: E731  (symmetric: forward and back)
    systems = []
    for at, image in zip(pixels, images):
        target = np.clip(np.asarray(image, dtype=np.float64), 0.0, None)
        target /= max(float(target.max()), 1e-12)
        index, weight = _splats(np.asarray(at, dtype=np.float64), target.shape)
        systems.append((target, index, weight, (blur(np.ones_like(target)).ravel()[index] * weight).sum(axis=1)))
    w = np.ones(len(pixels[0]))
    sensitivity = sum(s[3] for s in systems)
    for _ in range(iterations):
        back = 0.0
        for target, index, weight, _ in systems:
            drawn = blur(np.bincount(index.ravel(), (weight * w[:, None]).ravel(), target.size).reshape(target.shape))
            ratio = blur(target / np.maximum(drawn, 1e-6 * max(float(drawn.max()), 1e-12)))
            back = back + (ratio.ravel()[index] * weight).sum(axis=1)
        w = w * back / np.maximum(sensitivity, 1e-12)
    return w


def explaining(pixels: Sequence[np.ndarray], images: Sequence[np.ndarray]) -> np.ndarray:
    """Which voxels ``(N,)`` bool the images need: MLEM weight (:func:`explaining_weights`) at least :data:`FIT_SHARE`
    of the weights' 90th percentile."""
    if not len(pixels[0]):
        return np.zeros(0, dtype=bool)
    w = explaining_weights(pixels, images)
    return w >= FIT_SHARE * np.percentile(w, 90)
