"""One patient pose seen by both arms of a biplane system (numpy).

Each run's DICOM geometry (primary/secondary angle, SID, SOD) gives its C-arm pose
``A_v`` about the system's isocentre (``pose_from_carm_angles``); the two arms share
that isocentre, so one rigid *patient pose* ``X`` (isocentre frame -> centred CTA frame)
places both: ``T_v = X @ A_v``. ``X = I`` is the DICOM-angle start (the isocentre at the
CTA's centre). A single view fixes ``X`` only in its own image plane: its depth (along
the central ray) and its two out-of-plane rotations are nearly unobservable. The other
arm sees those in-plane, so :func:`fuse_patient_poses` combines per-view estimates of
``X`` weighting each component by how well its view observes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..dsa import DSARun
from ..geometry.detector import AP_REORIENT
from ..geometry.poses import axis_angle_to_matrix, invert, matrix_to_axis_angle, pose_from_carm_angles

__all__ = ["Observability", "nominal_poses", "patient_pose", "view_poses", "fuse_patient_poses", "central_ray",
           "common_axis", "turned_about", "moved_by", "part_way", "axis_disagreement_mm"]


@dataclass(frozen=True)
class Observability:
    """Relative weight of what one view sees: translation along its central ray (depth) and
    rotation about its two in-plane axes (out-of-plane), against 1 for the in-plane components."""

    depth: float = 0.02
    out_of_plane: float = 0.1


def nominal_poses(runs: Mapping[str, DSARun]) -> dict[str, np.ndarray]:
    """Each run's C-arm pose ``A_v`` ``(4, 4)`` about the isocentre, from its DICOM angles and distances."""
    return {key: pose_from_carm_angles(run.angles) for key, run in runs.items()}


def patient_pose(camera_pose: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """The patient pose ``X`` a view's camera pose implies: ``T_v = X @ A_v``."""
    return np.asarray(camera_pose, dtype=np.float64) @ invert(nominal)


def view_poses(X: np.ndarray, nominal: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Both camera poses ``X @ A_v`` of one patient pose."""
    return {key: np.asarray(X, dtype=np.float64) @ A for key, A in nominal.items()}


def _camera_axes(X: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """Columns: the view's camera x, y (in-plane) and z (central ray) axes in the CTA frame."""
    return (X @ nominal @ AP_REORIENT)[:3, :3]


def central_ray(X: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """Unit direction (CTA frame) of the central ray of the view ``nominal`` (``A_v``) at patient pose ``X``."""
    return _camera_axes(np.asarray(X, dtype=np.float64), nominal)[:, 2]


def fuse_patient_poses(
    estimates: Mapping[str, np.ndarray], nominal: Mapping[str, np.ndarray], observability: Observability = Observability()
) -> np.ndarray:
    """One patient pose from per-view estimates ``{view: X_v}``.

    The isocentre's position (``X[:3, 3]``, CTA frame, mm) is the information-weighted mean
    of the estimates, each view informing its in-plane directions fully and its depth with
    weight ``observability.depth``; the rotation likewise about the first estimate (in-plane
    rotation fully, out-of-plane with ``observability.out_of_plane``).
    """
    keys = list(estimates)
    ref = np.asarray(estimates[keys[0]], dtype=np.float64)
    info_t = np.zeros((3, 3))
    info_r = np.zeros((3, 3))
    sum_t = np.zeros(3)
    sum_r = np.zeros(3)
    for key in keys:
        X = np.asarray(estimates[key], dtype=np.float64)
        C = _camera_axes(X, nominal[key])
        w_t = C @ np.diag([1.0, 1.0, observability.depth]) @ C.T
        w_r = C @ np.diag([observability.out_of_plane, observability.out_of_plane, 1.0]) @ C.T
        info_t += w_t
        info_r += w_r
        sum_t += w_t @ X[:3, 3]
        sum_r += w_r @ matrix_to_axis_angle(X[:3, :3] @ ref[:3, :3].T)
    out = np.eye(4)
    out[:3, :3] = axis_angle_to_matrix(np.linalg.solve(info_r, sum_r)) @ ref[:3, :3]
    out[:3, 3] = np.linalg.solve(info_t, sum_t)
    return out


def common_axis(poses: Mapping[str, np.ndarray], nominal: Mapping[str, np.ndarray]) -> np.ndarray | None:
    """Unit vector (CTA frame) normal to the central rays of the first two views ``{view: X_v}``:
    the axis both image planes contain (superior-inferior for PA + lateral); None for one view
    or parallel arms."""
    if len(poses) < 2:
        return None
    (ka, Xa), (kb, Xb) = list(poses.items())[:2]
    common = np.cross(_camera_axes(np.asarray(Xa), nominal[ka])[:, 2], _camera_axes(np.asarray(Xb), nominal[kb])[:, 2])
    norm = np.linalg.norm(common)
    return None if norm < 1e-6 else common / norm


def turned_about(X: np.ndarray, axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """The patient pose ``X`` ``(4, 4)`` turned by ``angle_rad`` about the unit ``axis`` (CTA frame)
    through the isocentre (``X[:3, 3]`` stays)."""
    return moved_by(X, np.asarray(axis, dtype=np.float64) * angle_rad, np.zeros(3))


def moved_by(X: np.ndarray, rotation_rad: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    """The patient pose ``X`` turned by the axis-angle ``rotation_rad`` (CTA frame, through the
    isocentre) and its isocentre shifted by ``shift_mm``: the TTO's parameters of a patient pose."""
    out = np.array(X, dtype=np.float64)
    out[:3, :3] = axis_angle_to_matrix(np.asarray(rotation_rad, dtype=np.float64)) @ out[:3, :3]
    out[:3, 3] += np.asarray(shift_mm, dtype=np.float64)
    return out


def part_way(X: np.ndarray, Y: np.ndarray, fraction: float) -> np.ndarray:
    """The patient pose ``fraction`` of the way from ``X`` to ``Y`` (both ``(4, 4)``): the rotation
    between them (CTA frame, through ``X``'s isocentre) and the isocentre shift, both scaled."""
    X, Y = np.asarray(X, dtype=np.float64), np.asarray(Y, dtype=np.float64)
    turn = matrix_to_axis_angle(Y[:3, :3] @ X[:3, :3].T)
    return moved_by(X, fraction * turn, fraction * (Y[:3, 3] - X[:3, 3]))


def axis_disagreement_mm(estimates: Mapping[str, np.ndarray], nominal: Mapping[str, np.ndarray]) -> float:
    """How far apart (mm) two views put the isocentre along the direction both see in-plane
    (:func:`common_axis`); 0 for parallel arms."""
    axis = common_axis(estimates, nominal)
    if axis is None:
        return 0.0
    (_, Xa), (_, Xb) = list(estimates.items())[:2]
    return float(abs(np.dot(axis, np.asarray(Xa)[:3, 3] - np.asarray(Xb)[:3, 3])))
