"""Which pose a registration returns (``trust.py``): how far the stages' poses agree."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import RIG, _rotation


def test_stage_agreement_measures_the_patient_not_the_source():
    """A 6.4 deg turn of the patient about the CTA centre moves the PA source by about 73 mm but
    the CTA centre in the camera frame by nothing: the quality rule's agreement sees 6.4 deg / 0 mm;
    a shift of the patient reads as its length."""
    from geopose.register.trust import stage_agreement

    learned = RIG["pa"]
    turn = np.eye(4)
    turn[:3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), 6.4)
    deg, mm = stage_agreement(learned, turn @ learned)
    assert deg == pytest.approx(6.4, abs=1e-6) and mm == pytest.approx(0.0, abs=1e-9)
    assert np.linalg.norm((turn @ learned)[:3, 3] - learned[:3, 3]) > 70.0
    shift = np.eye(4)
    shift[:3, 3] = [3.0, -4.0, 11.0]
    deg, mm = stage_agreement(learned, shift @ learned)
    assert deg == pytest.approx(0.0, abs=1e-4) and mm == pytest.approx(np.linalg.norm(shift[:3, 3]), abs=1e-9)


def test_the_tto_result_gives_way_when_evidence_is_weak_or_its_vessels_miss_a_run():
    """The TTO's result stays unless its best objective is above ``WEAK_OBJECTIVE`` or, on a given segmentation, a
    view's vessel NCC is below ``VESSEL_NCC_FAILED`` (the weaker view named); a result the stages agree on with
    vessels in both runs stays."""
    from geopose.register.quality import VESSEL_NCC_FAILED
    from geopose.register.trust import COMPUTED_VESSELS_OBJECTIVE, WEAK_OBJECTIVE, tto_distrusted

    poses = {key: RIG[key] for key in ("pa", "lat")}
    strong = min(WEAK_OBJECTIVE, COMPUTED_VESSELS_OBJECTIVE) - 0.2
    assert tto_distrusted(poses, poses, strong, computed_vessels=False, vessel_ncc={"pa": 0.3, "lat": 0.2}) is None
    assert tto_distrusted(poses, poses, strong, computed_vessels=False) is None
    weak = tto_distrusted(poses, poses, WEAK_OBJECTIVE + 0.05, computed_vessels=False, vessel_ncc={"pa": 0.3, "lat": 0.2})
    assert weak is not None and "little image evidence" in weak
    missed = tto_distrusted(poses, poses, strong, computed_vessels=False,
                            vessel_ncc={"pa": VESSEL_NCC_FAILED - 0.01, "lat": VESSEL_NCC_FAILED - 0.04})
    assert missed is not None and "LAT run shows none" in missed and f"{VESSEL_NCC_FAILED - 0.04:.2f}" in missed
    assert tto_distrusted(poses, poses, strong, computed_vessels=False, vessel_ncc={"pa": None, "lat": 0.2}) is None
    # a computed mask's vessel NCC stays low at the truth: it is not read there (as the quality flag does not)
    assert tto_distrusted(poses, poses, strong, computed_vessels=True, vessel_ncc={"pa": 0.05, "lat": 0.05}) is None


def test_on_computed_vessels_a_weakly_matched_tto_result_gives_way_to_the_networks_estimate():
    """On a vessel mask computed from the CTA a result whose objective is above ``COMPUTED_VESSELS_OBJECTIVE`` gives way
    to the networks' estimate (the note gives the objective and the move, 8 deg); below it the result stays however far
    it moved; with a given segmentation the same weak result stays (only ``WEAK_OBJECTIVE`` applies there)."""
    from geopose.register.trust import COMPUTED_VESSELS_OBJECTIVE, WEAK_OBJECTIVE, tto_distrusted

    learned = {key: RIG[key] for key in ("pa", "lat")}
    turn = np.eye(4)
    turn[:3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), 8.0)
    far = {key: turn @ pose for key, pose in learned.items()}
    weak = COMPUTED_VESSELS_OBJECTIVE + 0.05
    assert weak < WEAK_OBJECTIVE
    reason = tto_distrusted(learned, far, weak, computed_vessels=True)
    assert reason is not None and f"objective {weak:.3f} > {COMPUTED_VESSELS_OBJECTIVE:g}" in reason
    assert "moved the networks' estimate by 8.0 deg" in reason
    assert tto_distrusted(learned, far, COMPUTED_VESSELS_OBJECTIVE - 0.05, computed_vessels=True) is None
    assert tto_distrusted(learned, far, weak, computed_vessels=False) is None
