"""The mirrored-CTA test (``register/mirror.py``): the hypothesis reflects the head across its own midplane
(``cta/symmetry.py``), and on a phantom with a
one-sided injection the CTA as given beats its mirror image while a CTA whose sides are swapped loses to it."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import _prepared

from geopose.geometry import invert
from geopose.register import TTOSchedule, test_time_optimise as run_tto
from geopose.register.biplane import nominal_poses
from geopose.cta.symmetry import Midplane, midsagittal_plane
from geopose.register.mirror import (EQUAL_EFFORT_FAIL_MARGIN, MIRROR_LOSS_MARGIN, MIRROR_TTO_ITERATIONS, MirrorTest,
                                     mirror_test, mirrored_volume)
from geopose.register.objective import pair_objective
from geopose.register.opacified import selection_judge
from geopose.register.tournament import Tournament
from geopose.register.tto import tto_views
from geopose.render.renderer import TorchRenderer
from geopose.render.volume import RenderVolume
from geopose.volume import Volume


YAW_DEG = 6.0


def _tilted_head() -> tuple[Volume, np.ndarray, np.ndarray, np.ndarray]:
    """A skull-like ellipsoid (semi-axes 50 / 62 / 40 mm, 1000 HU shell, 40 HU inside) turned 6 deg about S, its
    centre 9 mm left of the grid's, on a 2 mm LPS grid; a 300 HU rod 25 mm right of its midplane. Returns the CTA,
    the rod mask, the head's rotation and centre (LPS mm)."""
    shape = (48, 72, 64)  # k, j, i
    lps = np.stack(np.indices(shape)[::-1], axis=-1) * 2.0  # (k, j, i, 3): i, j, k -> x, y, z (mm)
    turn = np.radians(YAW_DEG)
    rotation = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
    centre = np.array([72.0, 72.0, 48.0])
    local = (lps - centre) @ rotation
    r = np.sqrt(((local / [50.0, 62.0, 40.0]) ** 2).sum(-1))
    rod = (np.hypot(local[..., 0] + 25.0, local[..., 1]) <= 3.0) & (np.abs(local[..., 2]) <= 10.0)
    hu = np.where(r <= 1.0, np.where(r > 0.88, 1000.0, 40.0), -1000.0) + np.where(rod, 260.0, 0.0)
    return Volume(hu.astype(np.float32), np.diag([-2.0, -2.0, 2.0, 1.0])), rod, rotation, centre


def _centroid_lps(mask: np.ndarray) -> np.ndarray:
    return np.argwhere(mask).mean(axis=0)[::-1] * 2.0


def test_the_mirrored_hypothesis_reflects_the_head_across_its_own_midplane():
    """A head turned 6 deg in the CT, off the grid's centre: the plane found is its own midplane (yaw 6 deg,
    roll 0, through its centre); mirrored, the head stays where it is and the rod on its right lies as far to its
    left; mirrored twice, the rod is back."""
    cta, rod, rotation, centre = _tilted_head()
    plane = midsagittal_plane(cta)
    assert plane.yaw_deg == pytest.approx(YAW_DEG, abs=1.0) and plane.roll_deg == pytest.approx(0.0, abs=1.0)
    assert abs(float((plane.point_lps_mm - centre) @ plane.normal_lps)) < 1.5 and plane.symmetry_ncc > 0.9
    head = cta.array > 0
    volume = RenderVolume(cta, {"cranium": cta.like(head.astype(np.uint8)), "vessels": cta.like(rod.astype(np.uint8))})
    mirrored = mirrored_volume(volume, plane)
    np.testing.assert_allclose(_centroid_lps(mirrored.mask("cranium")), _centroid_lps(head), atol=1.0)
    np.testing.assert_allclose(_centroid_lps(mirrored.mask("vessels")), centre + rotation @ [25.0, 0.0, 0.0], atol=1.5)
    assert mirrored.cta.array[tuple(np.argwhere(mirrored.mask("vessels")).mean(axis=0).round().astype(int))] > 200.0
    twice = mirrored_volume(mirrored, midsagittal_plane(mirrored.cta))
    np.testing.assert_allclose(_centroid_lps(twice.mask("vessels")), _centroid_lps(rod), atol=1.5)


def test_a_mirror_test_fails_a_result_only_when_the_mirror_image_explains_the_runs_better():
    plane = Midplane(np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.0, 0.0, 0.95)
    m = MIRROR_LOSS_MARGIN
    clear = MirrorTest(-1.00, -0.80, -0.90, plane)  # the CTA as given wins both comparisons by more than the bar
    assert clear.margin == pytest.approx(0.20) and clear.equal_effort_margin == pytest.approx(0.10)
    assert not clear.mirrored and clear.note is None and clear.reason is None
    assert clear.as_dict()["plane"]["symmetry_ncc"] == 0.95 and clear.as_dict()["short_loss"] == -0.90  # in the record
    # against the result: the mirror image ahead by more than the bar fails it, the equal-effort fit not run
    assert not MirrorTest(-1.00, -1.00 - 0.5 * m, -0.99, plane).mirrored
    beaten = MirrorTest(-1.00, -1.00 - 2.0 * m, None, plane)
    assert beaten.mirrored and beaten.equal_effort_margin is None and "against the result's -1.000" in beaten.reason
    # with equal effort: the result leans towards the CTA as given by what the whole registration gained over the short
    # fit; the mirror image ahead of the CTA's own short fit by more than twice the bar fails the result
    behind = MirrorTest(-1.00, -0.97, -0.97 + 2.5 * m, plane)
    assert behind.mirrored and "after the same 12 steps" in behind.reason
    assert not MirrorTest(-1.00, -0.97, -0.97 + 1.5 * m, plane).mirrored
    assert EQUAL_EFFORT_FAIL_MARGIN == pytest.approx(2 * m)
    # the sides-alike note: not failed, and either comparison leaves the mirror image within the bar or ahead
    alike = MirrorTest(-1.00, -1.00 + 0.6 * m, -0.99, plane).note  # within the bar of the result
    assert alike is not None and "left from its right" in alike and f"{0.6 * m:+.3f}" in alike
    assert MirrorTest(-1.00, -1.00 - 0.6 * m, -0.99, plane).note is not None
    leaning = MirrorTest(-1.00, -0.80, -0.80 - 0.5 * m, plane)  # ahead of the result, alike with equal effort
    assert not leaning.mirrored and leaning.note is not None and f"{0.5 * m:+.3f} with equal effort" in leaning.note
    assert beaten.note is None and behind.note is None  # a failed result gets the reason, not the note


def test_the_mirror_test_tells_a_one_sided_injection_from_its_mirror_image(unilateral_case):
    """Left ICA injection, the phantom's arteries as the segmentation, the networks' estimate at the truth: the CTA
    as given beats its mirror image by more than the margin; the same CTA with its sides swapped (the head in
    place, header kept) loses to its own mirror image, which is the patient."""
    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    X = truth.poses["pa"] @ invert(rig["pa"])
    schedule = TTOSchedule(MIRROR_TTO_ITERATIONS)

    def registered(r: TorchRenderer) -> Tournament:  # the CTA's own fit from the estimate, as the tournament judges it
        own = run_tto(r, tto_views(prep.views, truth.poses), schedule, rig=rig)
        loss = pair_objective(selection_judge(r, own.vessel_selection), own.poses, prep.views)
        return Tournament({"estimate": own}, {"estimate": loss}, "estimate", own.vessel_selection)

    swapped = TorchRenderer(mirrored_volume(renderer.volume, midsagittal_plane(renderer.volume.cta)))
    tournaments = {"correct": registered(renderer), "swapped": registered(swapped)}
    for factors in (None, (2, 2, 2)):  # on the TTO's own grid (2 mm), and on a 4 mm work grid (what a 1 mm CTA gets)
        correct = mirror_test(renderer, prep.views, tournaments["correct"], X, rig, factors=factors)
        assert correct.margin > MIRROR_LOSS_MARGIN and not correct.mirrored, (factors, correct.as_dict())
        assert correct.equal_effort_margin > MIRROR_LOSS_MARGIN and correct.note is None, (factors, correct.as_dict())
        flipped = mirror_test(swapped, prep.views, tournaments["swapped"], X, rig, factors=factors)
        assert flipped.mirrored and flipped.margin < -MIRROR_LOSS_MARGIN, (factors, flipped.as_dict())
        if factors is None:  # on the TTO's grid the result's loss is the tournament's own
            assert correct.loss == tournaments["correct"].objectives["estimate"]
