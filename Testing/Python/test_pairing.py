"""The pairing test (``register/pairing.py``): a tight vessel fit passes, the same vessels millimetres off fail, and
another subject's CTA registered with a phantom's runs comes out failed on the user's path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from register_helpers import _prepared

from geopose.register.cli import register_files
from geopose.register.pairing import BLUR_SIGMA_PX, GAIN_FAILED, GAIN_OK, PairingTest, pairing_test
from geopose.register.quality import assess


def test_the_gain_is_the_views_mean_and_grades_the_result_by_two_bars():
    tight = PairingTest({"pa": 0.60, "lat": 0.50}, {"pa": 0.66, "lat": 0.56})
    assert tight.gains == pytest.approx({"pa": 1.10, "lat": 1.12}) and tight.gain == pytest.approx(1.11)
    assert tight.verdict == "ok" and not tight.loose and tight.reason is None
    loose = PairingTest({"pa": 0.60, "lat": 0.50}, {"pa": 0.78, "lat": 0.62})
    assert loose.gain == pytest.approx(1.27) and loose.verdict == "failed" and loose.loose
    assert "one patient" in loose.reason and f"x{loose.gain:.2f}" in loose.reason and "only loosely" in loose.reason
    between = PairingTest({"pa": 0.60, "lat": 0.50}, {"pa": 0.72, "lat": 0.58})  # x1.18: between the bars
    assert GAIN_OK < between.gain < GAIN_FAILED and between.verdict == "doubtful" and not between.loose
    assert "usually do" in between.reason
    record = loose.as_dict()
    assert record["verdict"] == "failed" and record["gain_failed"] == GAIN_FAILED and record["blur_sigma_px"] == BLUR_SIGMA_PX
    # the flag: failed above the upper bar, doubtful between the bars, with the reason either way
    numbers = (0.6, 0.8, 1.0, 1.0)  # mNCC, silhouette Dice, the stages' agreement: nothing else against the result
    assert assess(*numbers, pairing=tight).flag == "ok"
    assert assess(*numbers, pairing=between).flag == "doubtful" and assess(*numbers, pairing=between).reasons == (between.reason,)
    assert assess(*numbers, pairing=loose).flag == "failed" and assess(*numbers, pairing=loose).reasons == (loose.reason,)
    # on a given segmentation (it may hold veins, which loosen a right pairing's fit too) a loose fit is only doubtful
    given = PairingTest(loose.ncc, loose.blurred_ncc, given_segmentation=True)
    assert given.verdict == "doubtful" and not given.loose and "only loosely" in given.reason
    assert "segmentation holds arteries only" in given.reason and "segmentation" not in loose.reason
    assert assess(*numbers, pairing=given).flag == "doubtful" and given.as_dict()["given_segmentation"]
    # a view whose vessels do not correlate at all carries no gain; with none left the test says nothing
    assert PairingTest({"pa": 0.60, "lat": -0.02}, {"pa": 0.66, "lat": 0.10}).gains == pytest.approx({"pa": 1.10})
    silent = PairingTest({"pa": 0.0, "lat": -0.1}, {"pa": 0.3, "lat": 0.2})
    assert silent.gain is None and silent.verdict == "ok"


def test_a_tight_fit_passes_and_the_same_vessels_millimetres_off_fail(phantom_case):
    """Phantom 12 (2 mm), its arteries as the segmentation: at the true poses the blur gains little; with the patient
    moved 3 mm up (both views see it) it gains more than the bar; 1 mm gains less than 3 mm."""
    truth, _, prep, renderer = _prepared(phantom_case)

    def moved(mm: float) -> PairingTest:
        shift = np.eye(4)
        shift[2, 3] = mm
        return pairing_test(renderer, {k: shift @ pose for k, pose in truth.poses.items()}, prep.views)

    at_truth, one, three = moved(0.0), moved(1.0), moved(3.0)
    assert at_truth.gain < GAIN_OK and at_truth.verdict == "ok", at_truth.as_dict()
    assert three.loose and three.gain > one.gain > at_truth.gain - 0.02, (one.as_dict(), three.as_dict())
    assert all(0.3 < v < 1.0 for v in at_truth.ncc.values())  # the vessels do correlate at the truth


@pytest.fixture(scope="module")
def two_subjects(tmp_path_factory) -> Path:
    """Phantoms 12 and 13 at 1.5 mm (fine enough for the artery classifier, which the test needs)."""
    from geopose.phantom.cli import write_phantom

    out = tmp_path_factory.mktemp("two_subjects")
    for seed in (12, 13):
        write_phantom(seed, out / str(seed), spacing_mm=1.5, max_matrix_px=512)
    return out


def test_another_subjects_cta_comes_out_failed_on_the_users_path(two_subjects, tmp_path):
    """``register_files`` with phantom 12's CTA and phantom 13's runs (the identifiers match, as anonymised files'
    may): both views failed, the pairing test's reason given; phantom 12's CTA with its own runs passes the test."""
    def registered(cta: int, runs: int) -> dict:
        folder = two_subjects / str(runs)
        return register_files(two_subjects / str(cta) / "cta.nii.gz", folder / "dsa_pa.dcm", folder / "dsa_lat.dcm",
                              tmp_path / f"{cta}-{runs}", progress=lambda *a: None)

    wrong, right = registered(12, 13), registered(12, 12)
    assert wrong["registration"]["pairing"]["verdict"] == "failed", wrong["registration"]["pairing"]
    for key in ("pa", "lat"):
        quality = wrong["views"][key]["quality"]
        assert quality["flag"] == "failed" and any("one patient" in r for r in quality["reasons"]), quality
    assert right["registration"]["pairing"]["gain"] < GAIN_OK, right["registration"]["pairing"]
    assert right["registration"]["pairing"]["gain"] < wrong["registration"]["pairing"]["gain"] - 0.2
    assert not any("one patient" in r for key in ("pa", "lat") for r in right["views"][key]["quality"]["reasons"])
