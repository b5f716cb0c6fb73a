"""The volume data contract: a voxel array, its index-to-RAS affine, and the centred frame.

Arrays are stored in numpy/SimpleITK order ``[k, j, i]`` (slowest axis first);
``ijk_to_ras`` maps homogeneous ``(i, j, k, 1)`` to patient RAS mm. Label maps
share the grid of the image they describe.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from .geometry.frames import centred_to_patient, grid_centre_ras

__all__ = ["Volume", "SHRINK_SLAB_SLICES", "index_points"]

#: Slices of the shrunk grid that :meth:`Volume.shrunk` computes at a time.
SHRINK_SLAB_SLICES = 32


def index_points(kji: np.ndarray, ijk_to_frame: np.ndarray) -> np.ndarray:
    """Points ``(N, 3)`` (mm) of array indices ``kji`` ``(N, 3)`` (``[k, j, i]`` order) under a 4x4 index -> frame map."""
    kji = np.asarray(kji)
    ijk1 = np.column_stack((kji[:, ::-1].astype(np.float64), np.ones(len(kji))))
    return (ijk1 @ np.asarray(ijk_to_frame).T)[:, :3]


@dataclass
class Volume:
    """A 3D scalar image on a regular grid (e.g. CTA in HU, or a label map)."""

    array: np.ndarray
    ijk_to_ras: np.ndarray
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ijk_to_ras = np.asarray(self.ijk_to_ras, dtype=float)
        if self.array.ndim != 3:
            raise ValueError(f"a volume is a 3D array, got shape {self.array.shape}")
        if self.ijk_to_ras.shape != (4, 4):
            raise ValueError("ijk_to_ras must be a 4x4 matrix")

    @property
    def shape_ijk(self) -> tuple[int, int, int]:
        k, j, i = self.array.shape
        return (i, j, k)

    @property
    def spacing_mm(self) -> tuple[float, float, float]:
        """Voxel size along i, j, k (mm)."""
        return tuple(float(v) for v in np.linalg.norm(self.ijk_to_ras[:3, :3], axis=0))

    @property
    def centre_ras(self) -> np.ndarray:
        return grid_centre_ras(self.ijk_to_ras, self.shape_ijk)

    @property
    def ijk_to_centred(self) -> np.ndarray:
        """4x4 from voxel index to the centred world frame (RAS axes, grid centre at 0)."""
        return np.linalg.inv(self.centred_to_ras) @ self.ijk_to_ras

    @property
    def centred_to_ras(self) -> np.ndarray:
        return centred_to_patient(self.ijk_to_ras, self.shape_ijk, "RAS")

    def centred_points(self, kji: np.ndarray) -> np.ndarray:
        """Voxel centres ``(N, 3)`` (centred frame, mm) of array indices ``kji`` ``(N, 3)`` (``[k, j, i]`` order)."""
        return index_points(kji, self.ijk_to_centred)

    @property
    def extent_mm(self) -> np.ndarray:
        """Physical size along i, j, k (mm), edge to edge."""
        return np.asarray(self.shape_ijk) * np.asarray(self.spacing_mm)

    def shrunk(self, factors: tuple[int, int, int] | list[int], dtype: type | None = None) -> "Volume":
        """Block means over ``factors`` (i, j, k) of the voxels (as ``dtype`` when given), exactly as ``sitk.BinShrink``
        computes them: whole blocks only (a partial block at a far edge is dropped), each voxel at its block's centre.
        Shrunk slab by slab, so no full-size copy is made (a 512^3 CTA is 0.5 GB). Itself when every factor is 1 and
        no ``dtype`` is asked for."""
        factors = [int(f) for f in factors]
        if max(factors) == 1 and dtype is None:
            return self
        fi, fj, fk = factors
        whole = self.array.shape[0] - self.array.shape[0] % fk
        step = SHRINK_SLAB_SLICES * fk
        shrunk = np.concatenate([
            sitk.GetArrayFromImage(sitk.BinShrink(sitk.GetImageFromArray(
                np.ascontiguousarray(self.array[k0:min(whole, k0 + step)], dtype=dtype)), factors))
            for k0 in range(0, whole, step)])
        centres = np.diag([fi, fj, fk, 1.0])
        centres[:3, 3] = (np.asarray(factors, dtype=np.float64) - 1.0) / 2.0
        return Volume(shrunk, self.ijk_to_ras @ centres, dict(self.metadata))

    def like(self, array: np.ndarray, **metadata) -> "Volume":
        """A volume on the same grid with other voxels (e.g. a label map)."""
        if array.shape != self.array.shape:
            raise ValueError(f"array shape {array.shape} does not match the grid {self.array.shape}")
        return Volume(array, self.ijk_to_ras.copy(), dict(metadata))
