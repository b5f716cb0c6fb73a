"""The TTO's common-axis search (``axis_search.py``): the valley turn about the axis both image planes
contain."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import RIG, _patient

from geopose.geometry.detector import Detector
from geopose.geometry.poses import project_points
from geopose.register.axis_search import valley_turn
from geopose.register.biplane import common_axis, moved_by


def test_the_valley_turn_moves_the_projections_least_and_the_tto_moves_along_it():
    """Along the common-axis valley (the turn with the other parameters' compensation) a head's
    points move less in both views than under the bare turn or any other compensation; the
    TTO's parameters follow it as ``moved_by`` does; one view or no points: no valley."""
    torch = pytest.importorskip("torch")
    from geopose.register.tto import _PatientParams

    g = np.random.default_rng(3)
    X = _patient()
    # vessels (mm, CTA frame): a cloud 40 mm from the isocentre, which a turn about it sweeps sideways
    # (measured: 0.47 px per degree along the valley, 0.61 for the bare turn)
    points = X[:3, 3] + [25.0, 20.0, 25.0] + g.normal(0.0, 1.0, (400, 3)) * [30.0, 20.0, 25.0]
    detectors = {key: Detector.model() for key in RIG}
    axis = common_axis({"pa": X, "lat": X}, RIG)

    def motion_px(rotation: np.ndarray, shift: np.ndarray, angle_rad: float = np.radians(1.0)) -> float:
        Y = moved_by(X, angle_rad * rotation, angle_rad * shift)
        return float(np.sqrt(np.mean([np.sum((project_points(Y @ RIG[k], detectors[k], points)[0]
                                              - project_points(X @ RIG[k], detectors[k], points)[0]) ** 2, axis=1)
                                      for k in RIG])))

    rotation, shift = valley_turn(X, RIG, detectors, points)
    assert rotation @ axis == pytest.approx(1.0)
    along = motion_px(rotation, shift)
    assert along < 0.85 * motion_px(axis, np.zeros(3)), (along, motion_px(axis, np.zeros(3)))
    normal = np.linalg.svd(axis[None])[2][1:]
    for _ in range(5):  # any other compensation moves the points more
        other = rotation + normal.T @ g.normal(0.0, 0.05, 2)
        assert motion_px(other, shift + g.normal(0.0, 3.0, 3)) > along
    assert valley_turn(X, {"pa": RIG["pa"]}, detectors, points) is None
    assert valley_turn(X, RIG, detectors, np.zeros((0, 3))) is None

    params = _PatientParams(X, RIG, "cpu")
    with torch.no_grad():
        params.move_along((params.w.detach().clone(), params.v.detach().clone()), (rotation, shift), 0.1)
        assert np.allclose(params.patient().numpy(), moved_by(X, 0.1 * rotation, 0.1 * shift), atol=1e-9)
