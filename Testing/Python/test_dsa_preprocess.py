"""DSA preprocessing (docs/conventions.md 5) on synthetic inputs with known answers."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from geopose import contract as C
from geopose.dsa import (
    DSARun,
    bilateral,
    bolus_weighted_mean,
    clip_intensities,
    dsa_cranium_mask,
    minmax,
    preprocess_dsa,
    resample_to_detector,
    resample_to_model_sdd,
    temporal_map,
)
from geopose.geometry import CArmAngles, Detector
from geopose.errors import InputError
from geopose.options import RegistrationOptions


def _disc(h: int, w: int, centre: tuple[float, float], radius: float) -> np.ndarray:
    r, c = np.mgrid[:h, :w]
    return (r - centre[0]) ** 2 + (c - centre[1]) ** 2 <= radius**2


def test_temporal_map_is_the_maximum_over_frames():
    rng = np.random.default_rng(0)
    frames = rng.uniform(0, 10, size=(6, 8, 9)).astype(np.float32)
    frames[4, 2, 3] = 50.0  # the bolus passes pixel (2, 3) at frame 4
    m = temporal_map(frames)
    assert m.shape == (8, 9) and m[2, 3] == 50.0
    for r, c in [(0, 0), (7, 8), (5, 1)]:
        assert m[r, c] == max(frames[t, r, c] for t in range(6))
    with pytest.raises(InputError):
        temporal_map(frames[0])


def _contrast_to_noise(image: np.ndarray, vessel: np.ndarray, inside: np.ndarray) -> float:
    background = image[inside & ~vessel]
    return float((image[vessel].mean() - background.mean()) / background.std())


def test_bolus_weighted_mean_keeps_the_vessels_and_drops_the_frames_without_contrast():
    """A vessel filled in 4 of 24 frames, noise in all: weighting the frames by the bolus read from
    the brightest pixels raises the vessel's contrast-to-noise ratio over the plain mean's by about
    sqrt(24 / 4); the vessel stays where it is."""
    rng = np.random.default_rng(3)
    h = w = 64
    inside = _disc(h, w, (32, 32), 28)
    vessel = np.zeros((h, w), dtype=bool)
    vessel[10:54, 30:33] = True
    bolus = np.zeros(24)
    bolus[6:10] = [0.5, 1.0, 1.0, 0.5]
    frames = 15.0 + rng.normal(0.0, 10.0, (24, h, w)) + 60.0 * bolus[:, None, None] * vessel
    weighted = bolus_weighted_mean(frames, inside, (1.0, 1.0))
    plain = frames.mean(axis=0)
    assert weighted.shape == (h, w) and weighted.dtype == np.float32
    gain = _contrast_to_noise(weighted, vessel, inside) / _contrast_to_noise(plain, vessel, inside)
    assert 1.6 < gain < 3.0
    assert np.argmax(weighted.mean(axis=0)) in (30, 31, 32)


def test_bolus_weighted_mean_follows_the_arteries_not_a_blush_that_outlasts_them():
    """A short run: a vessel filled in frames 1-2 of 7, then a capillary blush as wide as the head in frames
    3-6, brighter in the temporal mean than the vessel. The curve read from the frames' fine detail weights
    the arterial frames (the vessel stands out of the weighted image as in those frames); read from the
    plain frames it weighted the blush's and lost the vessel."""
    rng = np.random.default_rng(5)
    h = w = 96
    inside = _disc(h, w, (48, 48), 44)
    vessel = np.zeros((h, w), dtype=bool)
    vessel[30:66, 85:88] = True  # near the head's edge, where the blush is faint
    rows, cols = np.mgrid[0:h, 0:w]
    blush = np.sqrt(np.clip(1.0 - ((rows - 48.0) ** 2 + (cols - 48.0) ** 2) / 40.0 ** 2, 0.0, None))  # a chord of the head
    arterial, haze = np.array([0, 1, 1, 0, 0, 0, 0.0]), np.array([0, 0, 0, 1, 1, 1, 1.0])
    frames = (15.0 + rng.normal(0.0, 5.0, (7, h, w)) + 40.0 * arterial[:, None, None] * vessel
              + 60.0 * haze[:, None, None] * blush)
    mean = frames.mean(axis=0)
    assert mean[48, 48] > mean[vessel].max()  # the blush is the brighter in the temporal mean
    weighted = bolus_weighted_mean(frames, inside, pixel_mm=(1.0, 1.0))
    arterial_cnr = _contrast_to_noise(frames[1:3].mean(axis=0), vessel, inside)  # about 11
    assert _contrast_to_noise(weighted, vessel, inside) > 0.9 * arterial_cnr  # read from plain frames: -1.2


def test_bolus_weighted_mean_follows_the_arteries_not_the_motion_residue_that_grows_over_the_run():
    """A vessel filled in frames 2-4 of 12, and what a head that moves more and more leaves in the subtraction:
    a bright fringe along the vault's edge and noise over the whole head, both growing to the run's end. The
    fringe ranks among the temporal mean's brightest pixels, so the bolus curve rises to the last frames; over
    each frame's noise variance (the matched filter's weight) it keeps the arterial frames, and the vessel stands
    out of the weighted image about as far as from those frames (without the division: 0.77 and 0.24, the
    vessel lost to the fringe)."""
    rng = np.random.default_rng(7)
    h = w = 128
    inside = _disc(h, w, (64, 64), 58)
    fringe = inside & ~_disc(h, w, (64, 64), 55) & (np.mgrid[:h, :w][0] < 64)
    vessel = np.zeros((h, w), dtype=bool)
    vessel[40:90, 62:65] = True
    arterial = np.zeros(12)
    arterial[2:5] = [0.6, 1.0, 0.6]
    growth = (np.arange(12) / 11.0) ** 2
    for noise_growth in (10.0, 20.0):
        noise = rng.normal(0.0, 1.0, (12, h, w)) * (5.0 + noise_growth * growth)[:, None, None]
        frames = (15.0 + noise + 60.0 * arterial[:, None, None] * vessel + 30.0 * growth[:, None, None] * fringe)
        weighted = bolus_weighted_mean(frames.astype(np.float32), inside, (1.0, 1.0))
        background = inside & ~fringe
        arterial_cnr = _contrast_to_noise(frames[2:5].mean(axis=0), vessel, background)  # 11-13
        assert _contrast_to_noise(weighted, vessel, background) > 0.8 * arterial_cnr, noise_growth
        assert weighted[fringe].mean() - weighted[background & ~vessel].mean() < 5.0  # the fringe mostly gone


def test_bolus_weighted_mean_is_the_plain_mean_without_a_bolus():
    rng = np.random.default_rng(4)
    inside = _disc(32, 32, (16, 16), 12)
    still = np.repeat(rng.uniform(0, 50, (1, 32, 32)), 5, axis=0)  # every frame the same: a flat curve
    assert np.allclose(bolus_weighted_mean(still, inside, (1.0, 1.0)), still[0], atol=1e-4)
    one = rng.uniform(0, 50, (1, 32, 32))
    assert np.allclose(bolus_weighted_mean(one, inside, (1.0, 1.0)), one[0], atol=1e-4)
    with pytest.raises(InputError, match="mask is empty"):
        bolus_weighted_mean(one, np.zeros((32, 32), dtype=bool), (1.0, 1.0))


def test_cranium_mask_of_a_disc_is_the_disc():
    rng = np.random.default_rng(1)
    h, w = 120, 140
    disc = _disc(h, w, (60, 70), 45)
    image = np.where(disc, 100.0, 10.0) + rng.normal(0, 4, size=(h, w))
    image[50:60, 60:80] = 20.0  # a dark region inside the head: a hole to fill
    image[5:9, 5:9] = 100.0  # a bright speck outside: not the largest component
    mask = dsa_cranium_mask(image.astype(np.float32))
    assert mask.dtype == np.uint8
    iou = (mask.astype(bool) & disc).sum() / (mask.astype(bool) | disc).sum()
    assert iou > 0.97
    assert mask[55, 70] == 1 and mask[7, 7] == 0
    with pytest.raises(InputError, match="constant"):
        dsa_cranium_mask(np.ones((5, 5)))


def test_clip_uses_non_empty_columns_only():
    rng = np.random.default_rng(2)
    image = rng.uniform(0, 100, size=(30, 40)).astype(np.float32)
    support = np.zeros_like(image, dtype=bool)
    support[5:25, 10:30] = True
    lo, hi = np.percentile(image[:, 10:30], C.MAP_CLIP_PERCENTILES)
    out = clip_intensities(image, support)
    assert out.min() == pytest.approx(0.0)
    assert out.max() == pytest.approx(hi - lo, rel=1e-5)
    np.testing.assert_allclose(out, np.clip(image, lo, hi) - lo, rtol=1e-5, atol=1e-4)
    # columns outside the support (e.g. collimator) do not move the percentiles
    shaded = image.copy()
    shaded[:, :10] = 1e6
    np.testing.assert_allclose(clip_intensities(shaded, support)[:, 10:30], out[:, 10:30], rtol=1e-6)
    with pytest.raises(InputError, match="empty"):
        clip_intensities(image, np.zeros_like(support))


def _blob_centroid(image: np.ndarray) -> tuple[float, float]:
    w = np.clip(image, 0, None)
    r, c = np.mgrid[: image.shape[0], : image.shape[1]]
    return float((w * r).sum() / w.sum()), float((w * c).sum() / w.sum())


@pytest.mark.parametrize("offset", [(0.0, 0.0), (6.0, -9.0)])
def test_sdd_resampling_maps_a_point_to_the_expected_pixel(offset):
    """A point imaged at pixel (r, c) of a 600 x 500 px, 0.4 mm detector at SDD 1200 mm
    lies on the ray through camera (x, y, 1200); on the model detector (SDD 1020, 1.2 mm,
    256 px, no offset) the same ray hits (x, y) * 1020 / 1200."""
    src = Detector(600, 500, (0.4, 0.4), 1200.0, offset)
    r0, c0 = 180.0, 330.0
    rr, cc = np.mgrid[:600, :500]
    image = np.exp(-((rr - r0) ** 2 + (cc - c0) ** 2) / (2 * 4.0**2)).astype(np.float32)
    x = (249.5 - c0) * 0.4 + offset[0]
    y = (299.5 - r0) * 0.4 + offset[1]
    scale = C.MODEL_SDD_MM / 1200.0
    expected = (127.5 - y * scale / C.MODEL_PIXEL_SPACING_MM, 127.5 - x * scale / C.MODEL_PIXEL_SPACING_MM)
    out = resample_to_model_sdd(image, src)
    assert out.shape == (C.MODEL_DETECTOR_PX, C.MODEL_DETECTOR_PX)
    peak = np.unravel_index(np.argmax(out), out.shape)
    win = out[peak[0] - 6 : peak[0] + 7, peak[1] - 6 : peak[1] + 7]
    cr, cc_ = _blob_centroid(win)
    assert (peak[0] - 6 + cr, peak[1] - 6 + cc_) == pytest.approx(expected, abs=0.1)


def test_resampling_pads_outside_the_acquired_field():
    src = Detector(100, 100, (0.5, 0.5), 1000.0)  # 50 mm field: far smaller than the model's
    out = resample_to_model_sdd(np.ones((100, 100), np.float32), src)
    # the field spans 50 * 1020 / 1000 = 51 mm = 42.5 model pixels around the centre
    assert out[127, 127] == pytest.approx(1.0)
    assert out[0, 0] == 0.0 and out[127, 127 + 25] == 0.0 and out[127, 127 + 19] == pytest.approx(1.0)


def test_resampling_identity_geometry_is_identity():
    rng = np.random.default_rng(5)
    image = rng.uniform(size=(32, 40)).astype(np.float32)
    det = Detector(32, 40, (0.5, 0.6), 900.0)
    np.testing.assert_allclose(resample_to_detector(image, det, det), image, atol=1e-5)


def test_bilateral_keeps_a_step_and_smooths_noise():
    rng = np.random.default_rng(6)
    h, w = 96, 96
    clean = np.where(np.arange(w)[None, :] < w // 2, 0.0, 100.0) * np.ones((h, 1))
    noisy = (clean + rng.normal(0, 3.0, size=(h, w))).astype(np.float32)
    out = bilateral(noisy, C.BILATERAL_SPATIAL_SIGMA_PX, C.BILATERAL_RANGE_SIGMA)
    flat = out[:, 5:40]
    assert flat.std() < noisy[:, 5:40].std() / 3  # noise smoothed
    step = out[:, w // 2 + 1].mean() - out[:, w // 2 - 2].mean()
    assert step > 95  # edge kept
    blurred = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(noisy), C.BILATERAL_SPATIAL_SIGMA_PX))
    assert blurred[:, w // 2 + 1].mean() - blurred[:, w // 2 - 2].mean() < 30  # a plain blur would not keep it


def test_minmax_is_the_network_normalisation():
    out = minmax(np.array([[2.0, 4.0], [6.0, 10.0]], np.float32))
    np.testing.assert_allclose(out, [[0.0, 0.25], [0.5, 1.0]])
    assert np.all(minmax(np.full((3, 3), 7.0)) == 0.0)


def _synthetic_head_run(photometric: str = "MONOCHROME2") -> tuple[DSARun, np.ndarray, np.ndarray]:
    """A head (disc, attenuation 40) with a vessel that fills at frames 3..5 (attenuation +60),
    stored dark-on-bright as angiography shows it (MONOCHROME2) or as-is (MONOCHROME1)."""
    rng = np.random.default_rng(7)
    h, w, t = 200, 240, 6
    head = _disc(h, w, (100, 120), 80)
    vessel = np.zeros((h, w), bool)
    vessel[60:140, 115:121] = True
    att = np.zeros((t, h, w), np.float32)
    att[:] = np.where(head, 40.0, 0.0) + rng.normal(0, 1.0, size=(t, h, w))
    att[3:, vessel] += 60.0
    att -= att.min()
    stored = (att.max() - att) if photometric == "MONOCHROME2" else att
    det = Detector(h, w, (1.0, 1.0), 1100.0)
    run = DSARun(np.round(stored), det, CArmAngles(-5.0, 0.0, 1100.0, 750.0), 100.0, {"photometric_interpretation": photometric, "bits_stored": 8})
    return run, head, vessel


@pytest.mark.parametrize("photometric", ["MONOCHROME2", "MONOCHROME1"])
def test_preprocess_dsa_end_to_end(photometric):
    run, head, vessel = _synthetic_head_run(photometric)
    prep = preprocess_dsa(run, tto_px=120)
    # MAP: vessels and head bright whatever the stored polarity
    assert prep.map[vessel].mean() > prep.map[head & ~vessel].mean() + 40 > prep.map[~head].mean() + 70
    iou = (prep.mask.astype(bool) & head).sum() / (prep.mask.astype(bool) | head).sum()
    assert iou > 0.97
    # model geometry: 256 px of 1.2 mm at SDD 1020; the 160 mm head spans 160*1020/1100/1.2 px
    assert prep.model_image.shape == (256, 256) and prep.model_detector == Detector.model()
    assert 0.0 == prep.model_image.min() and prep.model_image.max() == pytest.approx(1.0)
    diameter_px = prep.model_mask[128].sum()
    assert diameter_px == pytest.approx(160 * C.MODEL_SDD_MM / 1100.0 / C.MODEL_PIXEL_SPACING_MM, abs=2)
    # masked before the bilateral filter (the order of docs/conventions.md 5): the outside stays near 0
    assert prep.model_image[prep.model_mask == 0].max() < 0.05
    # TTO target at the acquisition SDD, 120 px along the longer side
    assert prep.tto_detector.sdd_mm == 1100.0 and prep.tto_detector.shape == (100, 120)
    assert prep.tto_detector.size_mm == pytest.approx(run.detector.size_mm)
    assert prep.tto_image.shape == (100, 120) and prep.tto_mask.shape == (100, 120)
    # clipping to the interquartile range makes a silhouette: the head (and the vessel in it,
    # column 118 of 240 -> 59 of 120) saturates bright, the air around it is dark
    assert prep.tto_image[50, 58:61].mean() > 0.9 and prep.tto_image[50, 30] > 0.8
    assert prep.tto_image[50, 5] < 0.05 and prep.tto_image[2, 60] < 0.05
    assert prep.view_role == "PA" and prep.view_label == C.VIEW_PA


def test_a_milder_clip_for_the_networks_keeps_vessels_and_leaves_the_tto_target_alone():
    run, _, _ = _synthetic_head_run()
    paper = preprocess_dsa(run, tto_px=60)
    mild = preprocess_dsa(run, tto_px=60, model_clip_percentiles=(0.0, 100.0))
    np.testing.assert_array_equal(mild.tto_image, paper.tto_image)
    np.testing.assert_array_equal(mild.model_mask, paper.model_mask)
    inside = paper.model_mask > 0
    # 25-75: head and vessel saturate together; unclipped, the head (40) sits well below the vessel (100)
    assert np.median(paper.model_image[inside]) > 0.9
    assert np.median(mild.model_image[inside]) < 0.6 and mild.model_image.max() == pytest.approx(1.0)


@pytest.mark.parametrize("bad", [(75.0, 25.0), (-1.0, 50.0), (10.0, 101.0), (5.0,), "2-98"])
def test_bad_clip_percentiles_are_refused_with_the_rule(bad):
    run, _, _ = _synthetic_head_run()
    with pytest.raises(ValueError, match="clip percentiles"):
        preprocess_dsa(run, tto_px=60, model_clip_percentiles=bad)
    with pytest.raises(ValueError, match="model_clip_percentiles .*must"):
        RegistrationOptions(model_clip_percentiles=bad)


def test_preprocess_with_given_mask():
    run, head, _ = _synthetic_head_run()
    half = head.copy()
    half[:, 120:] = False
    prep = preprocess_dsa(run, mask=half, tto_px=60)
    np.testing.assert_array_equal(prep.mask, half.astype(np.uint8))
    assert prep.tto_mask[:, 35:].sum() == 0
    with pytest.raises(InputError, match="mask"):
        preprocess_dsa(run, mask=half[:, :100])
    with pytest.raises(InputError, match="empty"):
        preprocess_dsa(run, mask=np.zeros_like(half))


@pytest.mark.parametrize("sigma_px", [(4.0, 4.0), (2.36, 1.1), (0.0, 3.0), (0.0, 0.0)])
def test_blur_and_sample_grid_is_the_blur_then_the_bilinear_samples(sigma_px):
    """The separable form (two matrix products) gives what ITK's discrete Gaussian of the whole image, then
    bilinear samples (0 outside) at every grid point give: on a rough image, with samples outside every edge and
    within a kernel's reach of the edges (edge values repeated)."""
    from geopose.images import bilinear_sample, blur_and_sample_grid, gaussian_blur

    rng = np.random.default_rng(3)
    image = np.cumsum(rng.random((90, 70)), axis=0) + 5.0 * rng.random((90, 70))
    rows = np.linspace(-1.6, 91.2, 37)
    cols = np.linspace(70.4, -2.3, 23)  # reversed, as a detector's column axis may be
    want = bilinear_sample(gaussian_blur(image, sigma_px), *np.meshgrid(rows, cols, indexing="ij"))
    got = blur_and_sample_grid(image, rows, cols, sigma_px)
    assert got.shape == (37, 23) and (want == 0).any() and (want > 0).mean() > 0.8
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_wide_gaussian_blur_is_the_gaussian_of_its_sds():
    """An impulse blurred by the recursive filter keeps its sum, has the sd asked for along each axis (12 px along
    rows, 20 along columns; the recursive filter within 5 %) and is the sampled Gaussian within 2 % of its peak."""
    from geopose.images import wide_gaussian_blur

    impulse = np.zeros((201, 201))
    impulse[100, 100] = 1.0
    wide = wide_gaussian_blur(impulse, (12.0, 20.0))
    offsets = np.arange(201) - 100.0
    assert wide.sum() == pytest.approx(1.0, rel=0.01)
    assert np.sqrt((wide.sum(axis=1) * offsets ** 2).sum() / wide.sum()) == pytest.approx(12.0, rel=0.05)
    assert np.sqrt((wide.sum(axis=0) * offsets ** 2).sum() / wide.sum()) == pytest.approx(20.0, rel=0.05)
    exact = np.exp(-offsets[:, None] ** 2 / (2 * 12.0 ** 2) - offsets[None, :] ** 2 / (2 * 20.0 ** 2)) / (2 * np.pi * 240.0)
    assert np.abs(wide - exact).max() < 0.02 * exact.max()


@pytest.mark.parametrize("shape,radius_px", [((256, 256), 16), ((97, 130), 5), ((40, 33), 1), ((12, 50), 16)])
def test_disc_filter_is_itks_flat_ball_bit_for_bit(shape, radius_px):
    """The cranium mask's opening: a disc erosion and dilation from ITK line filters equal ITK's own ball filters
    bit for bit, at the image border and for a disc taller than the image; a bright pixel grows into the ball."""
    from geopose.images import disc_filter

    image = np.random.default_rng(radius_px).normal(size=shape).astype(np.float32)
    for erode, op in ((True, sitk.GrayscaleErode), (False, sitk.GrayscaleDilate)):
        want = sitk.GetArrayFromImage(op(sitk.GetImageFromArray(image), [radius_px] * 2, sitk.sitkBall))
        np.testing.assert_array_equal(disc_filter(image, radius_px, erode), want)
    spot = np.zeros((41, 41), np.float32)
    spot[20, 20] = 1.0
    grown = disc_filter(spot, 8, erode=False) > 0
    assert grown[20, 12] and grown[12, 20] and not grown[13, 13] and grown.sum() == pytest.approx(np.pi * 8.5 ** 2, rel=0.1)
