"""Similarity search of one patient pose seen by both arms (``search.py``)."""

from __future__ import annotations

import numpy as np
from conftest import blob_renderer
from register_helpers import RENDER_PX, RIG, _patient, _ray

from geopose.geometry.poses import rotation_angle_rad
from geopose.options import SearchOptions
from geopose.register import render_model_view
from geopose.register.biplane import moved_by, view_poses
from geopose.register.search import similarity_search


def test_similarity_search_recovers_shift_and_in_plane_turns_and_keeps_the_truth():
    renderer = blob_renderer()
    X_true = _patient()
    truth = view_poses(X_true, RIG)
    targets = {k: render_model_view(renderer, truth[k], RENDER_PX) for k in RIG}
    # Started at the truth: every neighbour scores lower, nothing moves; 10 moves per step size.
    kept = similarity_search(renderer, targets, X_true, RIG, RENDER_PX)
    assert kept.moves == () and kept.evaluations == 1 + 11 * len(SearchOptions.schedule)
    np.testing.assert_allclose(kept.patient_pose, X_true, atol=1e-12)
    # Off by a shift in every axis and a turn about each central ray (each view's in-plane rotation).
    start = moved_by(X_true, np.radians(3.0) * _ray("pa", X_true) - np.radians(2.0) * _ray("lat", X_true),
                     np.array([5.0, -3.0, 2.0]))
    found = similarity_search(renderer, targets, start, RIG, RENDER_PX)
    assert found.mncc > found.start_mncc + 0.05
    # Within the finest step of the truth (1 mm, 1 deg), from 6.2 mm and 3.6 deg.
    assert np.linalg.norm(found.patient_pose[:3, 3] - X_true[:3, 3]) <= 1.0
    assert np.degrees(rotation_angle_rad(found.patient_pose[:3, :3] @ X_true[:3, :3].T)) <= 1.0
    assert {name for name, _ in found.moves} <= {"shift x (mm)", "shift y (mm)", "shift z (mm)",
                                                  "turn about the PA ray (deg)", "turn about the LAT ray (deg)"}
    assert {abs(step) for _, step in found.moves} <= {step for step, _ in SearchOptions.schedule}
