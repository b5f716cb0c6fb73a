"""Batched rigid transforms (torch, float32 or float64).

A pose or transform is a ``(..., 4, 4)`` homogeneous matrix. Rotations are
parameterised either by Euler ZYX angles ``r = (rz, ry, rx)`` in rad with
``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` or by an axis-angle vector ``w`` (rad).
GeoPose's translation rule: ``T = [[R, R @ t], [0, 1]]``, i.e. ``t`` (mm) is
expressed in the rotated frame.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "RigidTransform",
    "euler_zyx_to_matrix",
    "matrix_to_euler_zyx",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "pose_from_params",
    "params_from_pose",
    "rotation_angle_rad",
    "as_transform",
]


def _rot(angle: Tensor, axis: int) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == 0:  # about x
        rows = (one, zero, zero, zero, c, -s, zero, s, c)
    elif axis == 1:  # about y
        rows = (c, zero, s, zero, one, zero, -s, zero, c)
    else:  # about z
        rows = (c, -s, zero, s, c, zero, zero, zero, one)
    return torch.stack(rows, dim=-1).reshape(*angle.shape, 3, 3)


def euler_zyx_to_matrix(r: Tensor) -> Tensor:
    """``(..., 3)`` Euler ZYX angles (rad) -> ``(..., 3, 3)`` rotation ``Rz @ Ry @ Rx``."""
    return _rot(r[..., 0], 2) @ _rot(r[..., 1], 1) @ _rot(r[..., 2], 0)


def matrix_to_euler_zyx(R: Tensor) -> Tensor:
    """Inverse of :func:`euler_zyx_to_matrix`; ``ry`` in ``[-pi/2, pi/2]``."""
    rz = torch.atan2(R[..., 1, 0], R[..., 0, 0])
    ry = torch.asin(torch.clamp(-R[..., 2, 0], -1.0, 1.0))
    rx = torch.atan2(R[..., 2, 1], R[..., 2, 2])
    return torch.stack((rz, ry, rx), dim=-1)


def _skew(w: Tensor) -> Tensor:
    zero = torch.zeros_like(w[..., 0])
    return torch.stack(
        (zero, -w[..., 2], w[..., 1], w[..., 2], zero, -w[..., 0], -w[..., 1], w[..., 0], zero), dim=-1
    ).reshape(*w.shape[:-1], 3, 3)


def axis_angle_to_matrix(w: Tensor) -> Tensor:
    """``(..., 3)`` axis-angle (rad) -> ``(..., 3, 3)`` rotation (Rodrigues, smooth at 0)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2.clamp_min(1e-30))
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-30))
    K = _skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """``(..., 3, 3)`` rotation -> ``(..., 3)`` axis-angle (rad), angle in ``[0, pi]``."""
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    v = torch.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1)
    sin = torch.sin(theta)
    small = theta < 1e-4
    scale = torch.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * sin.clamp_min(1e-12)))
    w = v * scale[..., None]
    # Near pi the antisymmetric part vanishes: take the axis from R + I instead.
    near_pi = theta > torch.pi - 1e-3
    if bool(near_pi.any()):
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        S = ((R + R.transpose(-1, -2)) / 2.0 - cos[..., None, None] * eye) / (1.0 - cos[..., None, None]).clamp_min(1e-12)
        diag = torch.diagonal(S, dim1=-2, dim2=-1)
        k = diag.argmax(-1, keepdim=True)
        col = torch.gather(S, -1, k[..., None, :].expand(*S.shape[:-1], 1))[..., 0]
        axis = col / col.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        sign = torch.sign((axis * v).sum(-1, keepdim=True))
        sign = torch.where(sign == 0, torch.ones_like(sign), sign)
        w = torch.where(near_pi[..., None], axis * sign * theta[..., None], w)
    return w


def rotation_angle_rad(R: Tensor) -> Tensor:
    """Geodesic angle (rad) of a ``(..., 3, 3)`` rotation."""
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    return torch.acos(((trace - 1.0) / 2.0).clamp(-1.0, 1.0))


def _homogeneous(R: Tensor, translation: Tensor) -> Tensor:
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = translation
    T[..., 3, 3] = 1.0
    return T


def pose_from_params(r: Tensor, t: Tensor, *, rotation: str = "euler_zyx") -> Tensor:
    """``(r, t)`` -> ``(..., 4, 4)`` with ``t`` (mm) in the rotated frame: ``[[R, R t], [0, 1]]``.

    ``rotation`` is ``"euler_zyx"`` (Init poses) or ``"axis_angle"`` (Refine residuals).
    """
    R = euler_zyx_to_matrix(r) if rotation == "euler_zyx" else axis_angle_to_matrix(r)
    return _homogeneous(R, (R @ t[..., None])[..., 0])


def params_from_pose(T: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`pose_from_params` (Euler ZYX): ``r = euler(R)``, ``t = R^T m``."""
    R = T[..., :3, :3]
    r = matrix_to_euler_zyx(R)
    t = (R.transpose(-1, -2) @ T[..., :3, 3:4])[..., 0]
    return r, t


class RigidTransform:
    """A batch of rigid transforms ``(B, 4, 4)``; composable with ``@``.

    ``A @ B`` applies ``B`` first. Points are ``(B, N, 3)`` or ``(N, 3)`` in mm.
    """

    def __init__(self, matrix: Tensor):
        m = torch.as_tensor(matrix)
        if m.shape[-2:] != (4, 4):
            raise ValueError(f"a rigid transform is a (..., 4, 4) matrix, got shape {tuple(m.shape)}")
        self.matrix = m if m.ndim == 3 else m.reshape(-1, 4, 4)

    # ---- constructors
    @classmethod
    def identity(cls, batch: int = 1, dtype: torch.dtype = torch.float32, device=None) -> "RigidTransform":
        return cls(torch.eye(4, dtype=dtype, device=device).expand(batch, 4, 4).clone())

    @classmethod
    def from_euler_zyx(cls, r: Tensor, t: Tensor) -> "RigidTransform":
        """GeoPose pose parameters: Euler ZYX (rad) and rotated-frame translation (mm)."""
        return cls(pose_from_params(r, t, rotation="euler_zyx"))

    @classmethod
    def from_axis_angle(cls, w: Tensor, t: Tensor) -> "RigidTransform":
        """Residual parameters: axis-angle (rad) and rotated-frame translation (mm)."""
        return cls(pose_from_params(w, t, rotation="axis_angle"))

    # ---- accessors
    @property
    def rotation(self) -> Tensor:
        return self.matrix[..., :3, :3]

    @property
    def translation(self) -> Tensor:
        """World-frame translation column (mm); not GeoPose's rotated-frame ``t``."""
        return self.matrix[..., :3, 3]

    def euler_zyx(self) -> tuple[Tensor, Tensor]:
        return params_from_pose(self.matrix)

    def __len__(self) -> int:
        return self.matrix.shape[0]

    def __getitem__(self, idx) -> "RigidTransform":
        return RigidTransform(self.matrix[idx])

    def to(self, *args, **kwargs) -> "RigidTransform":
        return RigidTransform(self.matrix.to(*args, **kwargs))

    # ---- algebra
    def __matmul__(self, other: "RigidTransform") -> "RigidTransform":
        return RigidTransform(self.matrix @ other.matrix)

    def inverse(self) -> "RigidTransform":
        R = self.rotation
        Rt = R.transpose(-1, -2)
        return RigidTransform(_homogeneous(Rt, -(Rt @ self.translation[..., None])[..., 0]))

    def apply(self, points: Tensor) -> Tensor:
        """Transform points ``(B, N, 3)`` (or ``(N, 3)``, broadcast over the batch)."""
        return points @ self.rotation.transpose(-1, -2) + self.translation[..., None, :]

    def apply_vectors(self, vectors: Tensor) -> Tensor:
        return vectors @ self.rotation.transpose(-1, -2)

    def __repr__(self) -> str:
        return f"RigidTransform(batch={len(self)}, dtype={self.matrix.dtype})"


def as_transform(pose: "RigidTransform | Tensor") -> RigidTransform:
    """Accept a :class:`RigidTransform` or a ``(..., 4, 4)`` tensor."""
    return pose if isinstance(pose, RigidTransform) else RigidTransform(torch.as_tensor(pose))
