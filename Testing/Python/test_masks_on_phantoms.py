"""The masks users will not have, computed from the data itself, against phantom truth:
the CTA cranium mask (from the CTA) and the DSA cranium mask (from the run's MAP)."""

from __future__ import annotations

import numpy as np
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_vessels import score  # noqa: E402  the benchmark's scoring, per vessel group

from geopose.cta import cranium_mask_from_cta, vessel_mask_from_cta  # noqa: E402
from geopose.dsa import dsa_cranium_mask, temporal_map
from geopose.phantom import labels as L
from geopose.phantom import make_subject
from geopose.phantom.dsa import dsa_renderer, sample_biplane, simulate_dsa


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.astype(bool), b.astype(bool)
    return 2.0 * (a & b).sum() / (a.sum() + b.sum())


@pytest.fixture(scope="module")
def subject():
    return make_subject(21, spacing_mm=2.0)


def test_cta_cranium_and_vessel_masks_match_phantom_truth(subject):
    cranium = cranium_mask_from_cta(subject.cta).array > 0
    truth = L.cranium_mask(subject.labels.array)
    assert _dice(cranium, truth) > 0.85  # 0.90 measured on seed 21: the bone mask also takes skull-base bone below the cranium label
    result = vessel_mask_from_cta(subject.cta)
    vessels = result.array > 0
    assert result.metadata["contrast"] is True
    assert "no artery classifier" in result.metadata["method"]  # a 2 mm grid: the threshold tree as it is (test_arteries: 1 mm)
    arteries = L.vessel_mask(subject.labels.array)
    neck = arteries & ~truth
    # An approximation (documented as such): it finds most arteries inside the cranium and in the neck
    # (the common, internal and external carotids and the vertebrals every run shows); seed 21 measured
    # 0.73 / 0.73, the mask before this one 0.73 / 0.02 (cranium only). Its precision stays low (venous
    # sinuses and facial bone plates share the 150-700 HU band), which is why a given segmentation is
    # preferred and the record says which one was used.
    assert (vessels & arteries & truth).sum() / (arteries & truth).sum() > 0.65
    assert (vessels & neck).sum() / neck.sum() > 0.5
    # the ICA's whole course, the petrous canal included (its lumen lies within the bone margin and is taken
    # back as a dark tube): 0.98 of the ICA centreline points within their radius (at least a voxel) of the mask
    # on seed 21, 0.73 before; the walls of the nasal cavity and sinuses are left out: precision 0.26, 0.18 before
    scores = score(vessels, subject.labels, subject.centerlines)
    assert scores["carotid_centreline_recall"] > 0.9
    assert scores["precision"] > 0.22


def test_vessel_mask_on_the_body_box_is_the_whole_grid_mask(subject):
    """The vessel rule runs on a box around the body: voxel for voxel what it gives on the whole grid, also where
    the body reaches the grid's edge (a grid cut through the head)."""
    from geopose.cta import masks

    axis, spacing = masks._superior_array_axis(subject.cta), subject.cta.spacing_mm
    hu = np.asarray(subject.cta.array, np.float32)
    for grid in (hu, hu[:, 20:, 10:-6]):
        body = masks.sitk.GetArrayFromImage(masks._largest_component(
            masks.sitk.GetImageFromArray((grid > masks.BODY_HU).astype(np.uint8)))).astype(bool)
        whole, whole_span = masks._vessel_mask_in_body(grid, body, spacing, axis)
        boxed, boxed_span = masks._vessel_mask(grid, spacing, axis)
        assert whole.sum() > 1000 and np.array_equal(boxed, whole) and boxed_span == whole_span
    assert np.prod([b.stop - b.start for b in masks._body_box(hu > masks.BODY_HU, spacing)]) < 0.8 * hu.size


def test_cranium_mask_on_the_bone_box_is_the_whole_grid_mask(subject, monkeypatch):
    """The cranium rule runs on the bone's box: the same mask as on the whole grid, also on a grid cut through the
    head (bone at its edges)."""
    from geopose.cta import masks

    from geopose.volume import Volume

    cut = Volume(np.ascontiguousarray(np.asarray(subject.cta.array)[:, 24:, 10:-6]), subject.cta.ijk_to_ras)
    boxed = [masks.cranium_mask_from_cta(cta).array for cta in (subject.cta, cut)]
    monkeypatch.setattr(masks, "_grown_box", lambda mask, grow, block=(1, 1, 1): tuple(slice(0, n) for n in mask.shape))
    whole = [masks.cranium_mask_from_cta(cta).array for cta in (subject.cta, cut)]
    for a, b in zip(boxed, whole):
        assert b.sum() > 10000 and np.array_equal(a, b)


def test_vessel_mask_on_the_body_box_keeps_the_skin_margin():
    """A lumen 2-3 mm under the body's outermost face is skin-deep on the whole grid and stays out on the body's
    box (which must reach past the body for that); one 10 mm deep is a vessel on both."""
    from geopose.cta import masks

    hu = np.full((60, 60, 60), -1000.0, np.float32)
    hu[10:50, 10:50, 10:50] = 40.0
    hu[29:31, 12:14, 15:45] = 300.0  # under the face at j = 10
    hu[29:31, 20:22, 15:45] = 300.0  # deep
    body = hu > masks.BODY_HU
    whole, _ = masks._vessel_mask_in_body(hu, body, (1.0, 1.0, 1.0), 0)
    boxed, _ = masks._vessel_mask(hu, (1.0, 1.0, 1.0), 0)
    assert np.array_equal(boxed, whole)
    assert whole[29:31, 20:22, 15:45].all() and whole.sum() == 2 * 2 * 30


def test_dsa_cranium_mask_matches_projected_cranium(subject):
    rng = np.random.default_rng(4)
    drr = dsa_renderer(subject, "cca_left")
    acqs, iso = sample_biplane(rng, subject)
    for acq in acqs:
        sim = simulate_dsa(subject, acq, acq.pose(iso), rng, injection="cca_left", drr=drr, max_matrix_px=256)
        mask = dsa_cranium_mask(temporal_map(sim.run.attenuation()))
        assert _dice(mask, sim.cranium_mask) > 0.9, acq.view_role  # 0.96 / 0.95 measured (PA / LAT)


def test_dsa_cranium_mask_survives_dense_opacification(subject):
    """Every artery opacified with five times the phantom world's contrast (an AVM, a late arterial phase):
    the vessels take the top of the run's 8-bit range and the head's noise-drawn level a few grey levels.
    Otsu on the MAP alone then masked the vessel tree (Dice 0.03-0.05 with the truth on the benchmark's
    dense phantoms, experiments/cranium_masks/cranium_masks.md); the mask must still be the head."""
    rng = np.random.default_rng(4)
    arch = dsa_renderer(subject, "arch")

    def dense(pose, detector):
        out = arch(pose, detector).clone()
        out[:, 2:] *= 5.0  # channels total, cranium, early and late arteries
        return out

    acqs, iso = sample_biplane(rng, subject)
    for acq in acqs:
        sim = simulate_dsa(subject, acq, acq.pose(iso), rng, injection="arch", drr=dense, max_matrix_px=256)
        image = temporal_map(sim.run.attenuation())
        dice = _dice(dsa_cranium_mask(image), sim.cranium_mask)
        assert dice > 0.88, (acq.view_role, dice)  # 0.95 / 0.93 measured (PA / LAT)


def test_the_body_erosion_is_itks_ball_erosion_voxel_for_voxel():
    """The vessel mask erodes the body with a distance map (faster); it must give exactly what
    ``sitk.BinaryErode`` with the ball of the same per-axis radii gives, at the grid's edges too."""
    import SimpleITK as sitk

    from geopose.cta.masks import _eroded_by_ball

    rng = np.random.default_rng(3)
    for radius in ([1, 1, 4], [2, 3, 2], [4, 2, 3], [5, 5, 5]):
        blobs = sitk.BinaryMedian(sitk.GetImageFromArray((rng.random((30, 36, 40)) > 0.45).astype(np.uint8)), [2, 2, 2])
        expected = sitk.GetArrayFromImage(sitk.BinaryErode(blobs, radius, sitk.sitkBall)).astype(bool)
        got = _eroded_by_ball(sitk.GetArrayFromImage(blobs).astype(bool), radius)
        assert 0 < expected.sum() < expected.size
        assert np.array_equal(got, expected), (radius, int((got != expected).sum()))


def test_the_cranium_closings_are_itks_closings_voxel_for_voxel():
    """The cranium mask closes the bone by a ball and bridges slices by a line without ITK's closing filter (faster);
    each must give exactly what ``sitk.BinaryMorphologicalClosing`` gives with that ball or box, at the grid's edges
    too."""
    import SimpleITK as sitk

    from geopose.cta.masks import _closed_along, _closed_by_ball

    rng = np.random.default_rng(5)
    for shape, radius in (((30, 36, 40), [1, 1, 4]), ((24, 30, 28), [2, 3, 2]), ((40, 20, 33), [4, 4, 4])):
        blobs = sitk.BinaryMedian(sitk.GetImageFromArray((rng.random(shape) > 0.6).astype(np.uint8)), [1, 1, 1])
        array = sitk.GetArrayFromImage(blobs).astype(bool)
        expected = sitk.GetArrayFromImage(sitk.BinaryMorphologicalClosing(blobs, radius, sitk.sitkBall)).astype(bool)
        assert array.sum() < expected.sum() < expected.size
        got = _closed_by_ball(array, radius)
        assert np.array_equal(got, expected), (radius, int((got != expected).sum()))
        for axis in range(3):
            for r in (1, 3, 6):
                line = [0, 0, 0]
                line[2 - axis] = r
                expected = sitk.GetArrayFromImage(sitk.BinaryMorphologicalClosing(blobs, line, sitk.sitkBox)).astype(bool)
                got = _closed_along(array, axis, r)
                assert np.array_equal(got, expected), (axis, r, int((got != expected).sum()))


def test_the_working_grid_is_one_binshrink_of_the_whole_ct_made_slab_by_slab():
    """The masks' working grid is shrunk slab by slab (no full-size copy of a 512^3 CTA); it must hold
    exactly the voxels and geometry of one ``sitk.BinShrink`` of the whole image, when the factors do not
    divide the grid too, and map a mask back onto the full grid by nearest neighbour (zero in the
    partial blocks BinShrink drops)."""
    import SimpleITK as sitk

    from geopose.cta.io import sitk_from_volume
    from geopose.cta.masks import _back_to_full
    from geopose.volume import SHRINK_SLAB_SLICES, Volume

    rng = np.random.default_rng(5)
    affine = np.array([[0.0, -0.45, 0.0, 12.0], [0.5, 0.0, 0.0, -40.0], [0.0, 0.0, 0.7, 3.0], [0.0, 0.0, 0.0, 1.0]])
    for shape, factors, dtype in (((2 * SHRINK_SLAB_SLICES * 3 + 5, 23, 17), [2, 3, 3], np.float32),
                                  ((70, 20, 26), [4, 2, 1], np.int16), ((9, 8, 8), [1, 1, 1], np.float32)):
        volume = Volume(rng.normal(0.0, 600.0, shape).astype(dtype), affine)
        expected = sitk.BinShrink(sitk_from_volume(volume), factors)
        shrunk = volume.shrunk(factors)
        work = sitk_from_volume(shrunk)
        assert np.array_equal(sitk.GetArrayFromImage(work), sitk.GetArrayFromImage(expected)), (shape, factors)
        assert work.GetSize() == expected.GetSize() and work.GetPixelID() == expected.GetPixelID()
        for a, b in ((work.GetOrigin(), expected.GetOrigin()), (work.GetSpacing(), expected.GetSpacing()),
                     (work.GetDirection(), expected.GetDirection())):
            np.testing.assert_allclose(a, b, atol=1e-9)
        mask = sitk.Cast(work > 0, sitk.sitkUInt8)
        reference = sitk.GetArrayFromImage(sitk.Resample(mask, sitk_from_volume(volume), sitk.Transform(),
                                                         sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8))
        full = _back_to_full(shrunk.like(sitk.GetArrayFromImage(mask)), volume)
        assert full.shape == volume.array.shape and np.array_equal(full, reference)
        k, j, i = (n - n % f for n, f in zip(shape, factors[::-1]))
        assert not full[k:].any() and not full[:, j:].any() and not full[:, :, i:].any()
