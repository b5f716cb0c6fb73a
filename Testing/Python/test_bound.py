"""``register/bound.py``: without vessel evidence the patient pose moves at most so far from the DICOM angles."""

from __future__ import annotations

import numpy as np
import pytest

from geopose.geometry.poses import axis_angle_to_matrix, matrix_to_axis_angle
from geopose.register.bound import MAX_ROTATION_DEG, MAX_SHIFT_MM, bound_move


def _pose(rotation_deg: float, shift_mm: float) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = axis_angle_to_matrix(np.radians(rotation_deg) * np.array([0.6, 0.0, 0.8]))
    X[:3, 3] = shift_mm * np.array([0.0, 1.0, 0.0])
    return X


def _turn_deg(X: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(matrix_to_axis_angle(X[:3, :3]))))


def test_a_move_within_the_bound_is_kept_as_it_is():
    X = _pose(0.5 * MAX_ROTATION_DEG, 0.5 * MAX_SHIFT_MM)
    move = bound_move(X)
    assert not move.bounded and move.fraction == 1.0
    np.testing.assert_array_equal(move.patient_pose, X)
    assert move.rotation_deg == pytest.approx(0.5 * MAX_ROTATION_DEG) and move.shift_mm == pytest.approx(0.5 * MAX_SHIFT_MM)


def test_a_larger_turn_is_scaled_back_onto_the_bound_along_the_same_axis():
    X = _pose(2.0 * MAX_ROTATION_DEG, 0.5 * MAX_SHIFT_MM)
    move = bound_move(X)
    assert move.bounded and move.fraction == pytest.approx(0.5)
    assert _turn_deg(move.patient_pose) == pytest.approx(MAX_ROTATION_DEG)
    axis = matrix_to_axis_angle(move.patient_pose[:3, :3])
    np.testing.assert_allclose(axis / np.linalg.norm(axis), [0.6, 0.0, 0.8], atol=1e-9)
    assert np.linalg.norm(move.patient_pose[:3, 3]) == pytest.approx(0.25 * MAX_SHIFT_MM)
    assert move.as_dict()["asked_rotation_deg"] == pytest.approx(2.0 * MAX_ROTATION_DEG)


def test_the_shift_bounds_too_and_the_tighter_bound_wins():
    move = bound_move(_pose(0.2 * MAX_ROTATION_DEG, 4.0 * MAX_SHIFT_MM))
    assert move.fraction == pytest.approx(0.25)
    assert np.linalg.norm(move.patient_pose[:3, 3]) == pytest.approx(MAX_SHIFT_MM)
    assert _turn_deg(move.patient_pose) == pytest.approx(0.05 * MAX_ROTATION_DEG)
