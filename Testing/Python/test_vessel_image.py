"""Which of a run's vessel images the objective compares (``register/vessel_image.py``), on the 2 mm phantom."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from register_helpers import _prepared

from geopose.dsa.preprocess import early_frames_mean
from geopose.images import gaussian_blur
from geopose.register.vessel_image import EARLY_IMAGE_LEAD, choose_vessel_images


def test_early_frames_mean_is_the_first_half_with_the_middle_frame():
    frames = np.arange(5, dtype=np.float32)[:, None, None] * np.ones((5, 2, 3), np.float32)
    np.testing.assert_allclose(early_frames_mean(frames), np.full((2, 3), 1.0))  # frames 0, 1, 2
    np.testing.assert_allclose(early_frames_mean(frames[:4]), np.full((2, 3), 0.5))  # frames 0, 1
    np.testing.assert_allclose(early_frames_mean(frames[:1]), np.zeros((2, 3)))


def test_a_broken_bolus_image_gives_way_to_the_runs_first_half_and_a_working_one_stays(phantom_case):
    """At the true poses both runs' bolus-weighted images work: each stays (the same object). A PA image that shows
    only the cranium's rim (what the capillary blush and motion residue left in 6010's lateral run) gives way to the
    run's first half, by more than the lead; the view handed back is a copy, the input untouched."""
    truth, _, prep, renderer = _prepared(phantom_case)
    views, choices = choose_vessel_images(renderer, prep.views, truth.poses)
    assert {k: c.used for k, c in choices.items()} == {"pa": "bolus", "lat": "bolus"}
    assert all(views[k] is prep.views[k] for k in views)
    assert all(c.ncc["bolus"] > 0.3 for c in choices.values()), choices

    pa = prep.views["pa"]
    inside = pa.tto_mask > 0
    rim = inside & (gaussian_blur(inside.astype(np.float64), (2.0, 2.0)) < 0.9)
    broken = {"pa": replace(pa, tto_vessels=rim.astype(np.float32)), "lat": prep.views["lat"]}
    views, choices = choose_vessel_images(renderer, broken, truth.poses)
    assert choices["pa"].used == "early" and choices["lat"].used == "bolus"
    assert choices["pa"].ncc["early"] >= choices["pa"].ncc["bolus"] + EARLY_IMAGE_LEAD
    assert views["pa"] is not broken["pa"] and views["pa"].tto_vessels is pa.tto_vessels_early
    np.testing.assert_array_equal(broken["pa"].tto_vessels, rim.astype(np.float32))
    assert views["lat"] is broken["lat"]

    # A view without an early image keeps its own and is not in the choice.
    views, choices = choose_vessel_images(renderer, {"pa": replace(pa, tto_vessels_early=None)}, truth.poses)
    assert views["pa"].tto_vessels is pa.tto_vessels and choices == {}
