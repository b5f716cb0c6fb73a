"""Similarity search of one patient pose seen by both arms (``search.py``)."""

from __future__ import annotations

import numpy as np
from conftest import blob_renderer
from register_helpers import RENDER_PX, RIG, _patient, _ray

from geopose.geometry.poses import rotation_angle_rad
from geopose.options import SearchOptions
from geopose.register import render_model_view
from geopose.register.biplane import moved_by, view_poses
from geopose.register.progress import Monitor
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


def test_similarity_search_never_scores_the_pose_it_just_left():
    renderer = blob_renderer()
    X_true = _patient()
    truth = view_poses(X_true, RIG)
    targets = {k: render_model_view(renderer, truth[k], RENDER_PX) for k in RIG}
    first = list(RIG)[0]
    scored: list[tuple] = []  # every patient pose scored, rounded to 1e-6
    render = renderer.render

    def recording(poses, *args, **kwargs):
        scored.append(tuple(np.round(np.asarray(poses)[0] @ np.linalg.inv(RIG[first]), 6)[:3].ravel()))
        return render(poses, *args, **kwargs)

    renderer.render = recording
    starts: list[int] = []  # where each step size began in ``scored`` (and where the search ended)
    monitor = Monitor(lambda stage, fraction, message: starts.append(len(scored)))
    start = moved_by(X_true, np.zeros(3), np.array([6.0, 0.0, 0.0]))
    found = similarity_search(renderer, targets, start, RIG, RENDER_PX, monitor=monitor)
    assert ("shift x (mm)", -4.0) in found.moves and found.evaluations == len(scored)
    # No pose is scored twice within a step size: the move back to the pose just left (it scored lower) is not tried.
    assert len(starts) == len(SearchOptions.schedule) + 1
    for begin, end in zip(starts, starts[1:]):
        assert len(set(scored[begin:end])) == end - begin
