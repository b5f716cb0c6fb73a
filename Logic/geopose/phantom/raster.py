"""Voxel grids in phantom coordinates, tube rasterisation and smooth random fields.

All shapes are evaluated at voxel centres expressed in *head coordinates* (mm,
RAS axes, origin at the centre of the brain; see ``anatomy``). A ``Grid`` maps
voxel indices to those coordinates, so the same anatomy can be rasterised on
the native grid (rotated, shifted, anisotropic) or on the canonical grid.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch.nn import functional as F

__all__ = ["Grid", "rasterise_tube", "SmoothField", "resample_polyline"]


@dataclass
class Grid:
    """A voxel grid ``shape_kji`` and the 4x4 map from index ``(i, j, k, 1)`` to head mm."""

    shape_kji: tuple[int, int, int]
    ijk_to_head: np.ndarray

    @cached_property
    def coords(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Head-frame x, y, z (mm) of every voxel centre, each ``(K, J, I)`` float32."""
        K, J, I = self.shape_kji
        m = self.ijk_to_head.astype(np.float32)
        i = np.arange(I, dtype=np.float32)[None, None, :]
        j = np.arange(J, dtype=np.float32)[None, :, None]
        k = np.arange(K, dtype=np.float32)[:, None, None]
        out = []
        for r in range(3):
            a = m[r, 2] * k + m[r, 3]
            b = m[r, 1] * j
            c = m[r, 0] * i
            out.append(((a + b) + c).astype(np.float32))
        return tuple(out)

    @cached_property
    def head_to_ijk(self) -> np.ndarray:
        return np.linalg.inv(self.ijk_to_head)

    @property
    def voxel_mm(self) -> float:
        """Geometric mean voxel size (mm), the width of partial-volume ramps."""
        return float(np.prod(np.linalg.norm(self.ijk_to_head[:3, :3], axis=0)) ** (1.0 / 3.0))

    def box(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice, slice] | None:
        """Index slices (k, j, i) covering the head-frame box ``[lo, hi]`` (mm), or None if outside."""
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        ijk = corners @ self.head_to_ijk.T
        a = np.floor(ijk[:, :3].min(0)).astype(int)
        b = np.ceil(ijk[:, :3].max(0)).astype(int) + 1
        K, J, I = self.shape_kji
        a = np.maximum(a, 0)
        b = np.minimum(b, (I, J, K))
        if np.any(b <= a):
            return None
        return (slice(a[2], b[2]), slice(a[1], b[1]), slice(a[0], b[0]))


def resample_polyline(points: np.ndarray, per_point: np.ndarray, step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 3)`` and per-point values ``(N,)`` or ``(N, M)`` (radii, HU) re-sampled at
    about ``step_mm`` along the arc length (values linearly interpolated)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    n = max(2, int(np.ceil(s[-1] / step_mm)) + 1)
    t = np.linspace(0.0, s[-1], n)
    pts = np.stack([np.interp(t, s, points[:, a]) for a in range(3)], axis=1)
    cols = per_point.reshape(len(points), -1)
    out = np.stack([np.interp(t, s, cols[:, a]) for a in range(cols.shape[1])], axis=1)
    return pts, out.reshape((n,) + per_point.shape[1:])


def rasterise_tube(
    grid: Grid,
    points: np.ndarray,
    radii: np.ndarray,
    coverage: np.ndarray,
    labels: np.ndarray | None = None,
    label: float = 0,
    min_cover: float = 0.5,
    values: np.ndarray | None = None,
    point_values: np.ndarray | None = None,
) -> None:
    """Add a tube (polyline ``(N, 3)`` head mm, radius per point mm) to ``coverage`` in place.

    Coverage is a partial-volume fraction in [0, 1] combined by maximum; where the
    tube covers more than ``min_cover`` of a voxel and more than before, ``labels``
    (a label map, or a value map) gets ``label``. Where it covers more than before
    (any share), ``values`` (a value map) gets ``point_values`` (one per point, e.g.
    HU), interpolated along the tube. Only the bounding box of each segment is touched.
    """
    X, Y, Z = grid.coords
    h = grid.voxel_mm
    step = float(np.clip(2.0 * np.max(radii), 1.5, 6.0))
    per_point = np.column_stack([radii, np.zeros(len(radii)) if point_values is None else point_values]).astype(float)
    pts, cols = resample_polyline(np.asarray(points, float), per_point, step)
    rad, val = cols[:, 0], cols[:, 1]
    for a, b, ra, rb, va, vb in zip(pts[:-1], pts[1:], rad[:-1], rad[1:], val[:-1], val[1:]):
        pad = max(ra, rb) + h
        sl = grid.box(np.minimum(a, b) - pad, np.maximum(a, b) + pad)
        if sl is None:
            continue
        d = (b - a).astype(np.float32)
        dd = float(d @ d) or 1e-9
        px, py, pz = X[sl] - a[0], Y[sl] - a[1], Z[sl] - a[2]
        t = np.clip((px * d[0] + py * d[1] + pz * d[2]) / dd, 0.0, 1.0)
        dist = np.sqrt((px - t * d[0]) ** 2 + (py - t * d[1]) ** 2 + (pz - t * d[2]) ** 2)
        r = ra + t * (rb - ra)
        cov = np.clip((r - dist) / h + 0.5, 0.0, 1.0) * np.minimum(1.0, 2.0 * r / h)
        cur = coverage[sl]
        more = cov > cur
        if labels is not None:
            lab = labels[sl]
            lab[(cov > min_cover) & more] = label
        if values is not None:
            v = values[sl]
            v[more] = (va + t * (vb - va))[more]
        np.maximum(cur, cov, out=cur)


class SmoothField:
    """A seeded smooth random field on head coordinates: unit-variance Gaussian
    noise on a lattice of ``cell_mm`` spacing, trilinearly interpolated."""

    #: Half-size (mm) of the cube the lattice covers (head coordinates).
    EXTENT_MM = 260.0

    def __init__(self, rng: np.random.Generator, cell_mm: float):
        n = int(np.ceil(2 * self.EXTENT_MM / cell_mm)) + 1
        self.lattice = torch.from_numpy(rng.standard_normal((1, 1, n, n, n)).astype(np.float32))

    def __call__(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Field values at head-frame points (mm), same shape as ``x``."""
        g = torch.from_numpy(np.stack((x, y, z), axis=-1).reshape(1, -1, 1, 1, 3) / np.float32(self.EXTENT_MM))
        v = F.grid_sample(self.lattice, g, mode="bilinear", padding_mode="border", align_corners=True)
        return v.reshape(x.shape).numpy()

    def on_grid(self, grid: Grid, step_mm: float) -> np.ndarray:
        """The field on every voxel of ``grid``, sampled about every ``step_mm`` and
        trilinearly upsampled (the field is smooth on that scale)."""
        f = max(1, int(step_mm // grid.voxel_mm))
        X, Y, Z = (c[::f, ::f, ::f] for c in grid.coords)
        coarse = torch.from_numpy(np.ascontiguousarray(self(X, Y, Z)))
        if f == 1:
            return coarse.numpy()
        # the coarse samples sit on voxels 0, f, 2f, ...; the stretch to the last voxel is < f voxels
        full = F.interpolate(coarse[None, None], size=grid.shape_kji, mode="trilinear", align_corners=True)[0, 0]
        return full.contiguous().numpy()
