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
