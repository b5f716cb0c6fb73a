"""Pose algebra in numpy (float64): the poses every registration stage passes on.

Euler ZYX ``R = Rz @ Ry @ Rx`` and axis-angle rotations in rad, GeoPose's
rotated-frame translation ``T = [[R, R t], [0, 1]]`` in mm, camera-to-world poses
``world = T @ AP_REORIENT @ camera`` in the centred CTA frame (docs/conventions.md
sections 1-2). Arrays broadcast over leading axes. The differentiable torch algebra
(training, the test-time optimisation) is ``rigid.py``; the two are tested equal.
"""

from __future__ import annotations

import numpy as np

from .. import contract as C
from .detector import AP_REORIENT, CArmAngles, Detector, carm_angles_from_params, carm_pose_params

__all__ = [
    "euler_zyx_to_matrix",
    "matrix_to_euler_zyx",
    "params_from_pose",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "pose_from_params",
    "invert",
    "rotation_angle_rad",
    "isopose",
    "pose_from_carm_angles",
    "carm_angles_from_pose",
    "source_and_detector_points",
    "project_points",
]


def _rot(angle: np.ndarray, axis: int) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(angle), np.zeros_like(angle)
    rows = {
        0: (one, zero, zero, zero, c, -s, zero, s, c),
        1: (c, zero, s, zero, one, zero, -s, zero, c),
        2: (c, -s, zero, s, c, zero, zero, zero, one),
    }[axis]
    return np.stack(rows, axis=-1).reshape(*np.shape(angle), 3, 3)


def euler_zyx_to_matrix(r: np.ndarray) -> np.ndarray:
    """``(..., 3)`` Euler ZYX angles (rad) -> ``(..., 3, 3)`` rotation ``Rz @ Ry @ Rx``."""
    r = np.asarray(r, dtype=np.float64)
    return _rot(r[..., 0], 2) @ _rot(r[..., 1], 1) @ _rot(r[..., 2], 0)


def matrix_to_euler_zyx(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_zyx_to_matrix`; ``ry`` in ``[-pi/2, pi/2]``."""
    R = np.asarray(R, dtype=np.float64)
    return np.stack(
        (np.arctan2(R[..., 1, 0], R[..., 0, 0]), np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0)), np.arctan2(R[..., 2, 1], R[..., 2, 2])),
        axis=-1,
    )


def axis_angle_to_matrix(w: np.ndarray) -> np.ndarray:
    """``(..., 3)`` axis-angle (rad) -> ``(..., 3, 3)`` rotation (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    theta2 = (w * w).sum(-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta2 < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    zero = np.zeros_like(w[..., 0])
    K = np.stack((zero, -w[..., 2], w[..., 1], w[..., 2], zero, -w[..., 0], -w[..., 1], w[..., 0], zero), -1)
    K = K.reshape(*w.shape[:-1], 3, 3)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (rad) of a rotation ``(3, 3)``; the angle in [0, pi)."""
    R = np.asarray(R, dtype=np.float64)
    angle = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return 0.5 * v if angle < 1e-8 else v * (angle / (2.0 * np.sin(angle)))


def pose_from_params(r: np.ndarray, t: np.ndarray, *, rotation: str = "euler_zyx") -> np.ndarray:
    """``(r, t)`` -> ``(..., 4, 4)`` ``[[R, R t], [0, 1]]``; ``rotation`` ``"euler_zyx"`` or ``"axis_angle"``."""
    R = euler_zyx_to_matrix(r) if rotation == "euler_zyx" else axis_angle_to_matrix(r)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = (R @ np.asarray(t, dtype=np.float64)[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def params_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pose_from_params` (Euler ZYX): ``r = euler(R)``, ``t = R^T m``."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    return matrix_to_euler_zyx(R), (np.swapaxes(R, -1, -2) @ T[..., :3, 3:4])[..., 0]


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid ``(..., 4, 4)`` transforms."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad) of ``(..., 3, 3)`` rotations."""
    trace = np.trace(np.asarray(R), axis1=-2, axis2=-1)
    return np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))


def isopose(view: int) -> np.ndarray:
    """Isocentric pose ``(4, 4)`` of a view label (0 LAT-, 1 PA, 2 LAT+)."""
    return pose_from_params(np.array([C.VIEW_ANCHOR_RAD[view], 0.0, 0.0]), np.array(C.ISO_TRANSLATION_MM))


def pose_from_carm_angles(angles: CArmAngles) -> np.ndarray:
    """DICOM positioner angles -> camera-to-world pose ``(4, 4)`` about the isocentre."""
    return pose_from_params(*carm_pose_params(angles))


def carm_angles_from_pose(pose: np.ndarray, sid_mm: float) -> CArmAngles:
    """Inverse of :func:`pose_from_carm_angles` for one pose ``(4, 4)``."""
    r, t = params_from_pose(np.asarray(pose, dtype=np.float64).reshape(4, 4))
    return carm_angles_from_params(r, t, sid_mm)


def source_and_detector_points(pose: np.ndarray, detector: Detector) -> tuple[np.ndarray, np.ndarray]:
    """World positions (mm) of the source ``(3,)`` and of every pixel ``(H, W, 3)`` for one pose ``(4, 4)``."""
    M = np.asarray(pose, dtype=np.float64) @ AP_REORIENT
    return M[:3, 3].copy(), detector.camera_points() @ M[:3, :3].T + M[:3, 3]


def project_points(pose: np.ndarray, detector: Detector, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(N, 3)`` -> pixels (row, col) and depth (mm along the axis): ``(N, 2)`` and ``(N,)``
    for one pose ``(4, 4)``, ``(B, N, 2)`` and ``(B, N)`` for poses ``(B, 4, 4)``."""
    world_to_cam = invert(np.asarray(pose, dtype=np.float64) @ AP_REORIENT)
    cam = np.asarray(points_mm, dtype=np.float64) @ np.swapaxes(world_to_cam[..., :3, :3], -1, -2)
    cam = cam + world_to_cam[..., None, :3, 3]
    return detector.camera_to_pixel(cam), cam[..., 2]
