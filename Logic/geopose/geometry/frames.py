"""The centred CTA frame and the patient (RAS / LPS) frame.

The centred frame has the patient-RAS axes and its origin at the RAS position of
voxel index ``(shape - 1) / 2`` (docs/conventions.md section 1). Poses are camera-to-world
in the centred frame; Slicer wants them camera-to-RAS.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RAS_TO_LPS", "grid_centre_ras", "centred_to_patient", "pose_to_patient", "pose_from_patient"]

#: RAS <-> LPS (its own inverse).
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def grid_centre_ras(ijk_to_ras: np.ndarray, shape_ijk: tuple[int, int, int]) -> np.ndarray:
    """RAS position (mm) of the voxel-grid centre, index ``(shape - 1) / 2`` (shape in i, j, k order)."""
    centre = (np.asarray(shape_ijk, dtype=float) - 1.0) / 2.0
    return (np.asarray(ijk_to_ras, dtype=float) @ np.append(centre, 1.0))[:3]


def centred_to_patient(ijk_to_ras: np.ndarray, shape_ijk: tuple[int, int, int], space: str = "RAS") -> np.ndarray:
    """4x4 mapping centred-frame points (mm) to patient RAS (or LPS) points."""
    m = np.eye(4)
    m[:3, 3] = grid_centre_ras(ijk_to_ras, shape_ijk)
    if space.upper() == "LPS":
        return RAS_TO_LPS @ m
    if space.upper() != "RAS":
        raise ValueError(f"space must be 'RAS' or 'LPS', got {space!r}")
    return m


def pose_to_patient(pose_centred: np.ndarray, ijk_to_ras: np.ndarray, shape_ijk, space: str = "RAS") -> np.ndarray:
    """Camera-to-centred pose(s) ``(..., 4, 4)`` -> camera-to-patient pose(s)."""
    return centred_to_patient(ijk_to_ras, shape_ijk, space) @ np.asarray(pose_centred, dtype=float)


def pose_from_patient(pose_patient: np.ndarray, ijk_to_ras: np.ndarray, shape_ijk, space: str = "RAS") -> np.ndarray:
    """Inverse of :func:`pose_to_patient`."""
    return np.linalg.inv(centred_to_patient(ijk_to_ras, shape_ijk, space)) @ np.asarray(pose_patient, dtype=float)
