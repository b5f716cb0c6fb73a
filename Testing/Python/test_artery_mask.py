"""The experimental artery segmentation (``geopose.cta.vessels``) on synthetic CTs: a contrast-filled
tube in soft tissue beside bone is found and the bone is not; a CT without contrast gives an empty
mask that says so."""

from __future__ import annotations

import numpy as np

from geopose.cta.vessels import artery_mask_from_cta
from geopose.volume import Volume


def _neck(lumen_hu: float) -> tuple[Volume, np.ndarray, np.ndarray]:
    """A 1 mm block of soft tissue (40 HU) with a vertical tube (radius 3 mm, ``lumen_hu``) and a
    bone slab (1500 HU cortex) 12 mm beside it; returns the CT, the tube and the slab ([k, j, i])."""
    n = 64
    k, j, i = np.mgrid[:n, :n, :n].astype(float)
    a = np.full((n, n, n), 40.0, np.float32)
    tube = np.hypot(j - 32, i - 26) <= 3.0
    slab = (i >= 41) & (i < 47)
    a[tube] = lumen_hu
    a[slab] = 1500.0
    a += np.random.default_rng(0).normal(0.0, 5.0, a.shape).astype(np.float32)
    return Volume(a, np.diag([1.0, 1.0, 1.0, 1.0])), tube, slab


def test_contrast_tube_is_found_and_bone_is_not():
    cta, tube, slab = _neck(400.0)
    result = artery_mask_from_cta(cta)
    mask = result.array > 0
    assert result.metadata["contrast"] is True
    assert (mask & tube).sum() / tube.sum() > 0.8
    assert not (mask & slab).any()
    assert (mask & ~tube).sum() < 0.3 * tube.sum()  # the half-maximum edge: a partial-volume rim at most


def test_ct_without_contrast_gives_an_empty_mask_that_says_so():
    cta, _, _ = _neck(45.0)  # blood without contrast
    result = artery_mask_from_cta(cta)
    assert not result.array.any()
    assert result.metadata["contrast"] is False
    assert "no contrast-filled tree" in result.metadata["method"]
