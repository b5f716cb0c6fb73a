"""The numpy ray-marching kernel (no PyTorch): the same line integrals as :class:`~geopose.render.drr.DRR`.

Rays go from the source to every pixel, are clipped to the voxel box ``[-0.5, n - 0.5]``
and sampled at ``n`` midpoints (``n = ceil(longest chord / step)``); a pixel is
``sum(trilinear density) * chord / n`` (density x mm). Ray chunks run on a thread pool
(numpy releases the GIL in its gathers and arithmetic), so every core is used.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..geometry.detector import Detector
from ..geometry.poses import source_and_detector_points
from .work import count

__all__ = ["NumpyKernel", "CHUNK_SAMPLES"]

#: Samples (rays x steps) processed per chunk.
CHUNK_SAMPLES = 1 << 17


def _threads() -> int:
    return max(1, min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))


class NumpyKernel:
    """Line integrals of a ``(C, K, J, I)`` float32 density grid; ``ijk_to_world`` (4x4) maps
    voxel indices to the centred frame (mm); ``step_mm`` is the sampling step."""

    def __init__(self, density: np.ndarray, ijk_to_world: np.ndarray, step_mm: float) -> None:
        density = np.asarray(density, dtype=np.float32)
        if density.ndim != 4:
            raise ValueError(f"density must be (C, K, J, I), got {density.shape}")
        self.channels, K, J, I = density.shape
        self.shape_ijk = (I, J, K)
        # Per channel, zero-padded by one voxel: a trilinear corner is one flat index away.
        self._padded = [np.pad(c, 1).ravel() for c in density]
        self.world_to_ijk = np.linalg.inv(np.asarray(ijk_to_world, dtype=np.float64))
        self.step_mm = float(step_mm)
        self._row, self._plane = I + 2, (J + 2) * (I + 2)
        self._pool = ThreadPoolExecutor(_threads())

    def __call__(self, pose: np.ndarray, detector: Detector, channels: tuple[int, ...]) -> np.ndarray:
        """``(C', H, W)`` float32 for one pose ``(4, 4)`` on ``detector``."""
        src, pix = source_and_detector_points(np.asarray(pose, dtype=np.float64).reshape(4, 4), detector)
        H, W = detector.shape
        pix = pix.reshape(-1, 3)
        s = self.world_to_ijk[:3, :3] @ src + self.world_to_ijk[:3, 3]
        seg = pix @ self.world_to_ijk[:3, :3].T + self.world_to_ijk[:3, 3] - s
        lo, hi = _clip_to_box(s, seg, self.shape_ijk)
        chord_mm = (hi - lo) * np.linalg.norm(pix - src, axis=1)
        n = max(1, int(math.ceil(float(chord_mm.max()) / self.step_mm)))
        frac = ((np.arange(n) + 0.5) / n).astype(np.float32)
        count(1, len(pix), n, len(channels))
        start = (s + lo[:, None] * seg).astype(np.float32)
        span = ((hi - lo)[:, None] * seg).astype(np.float32)
        values = [self._padded[c] for c in channels]
        chunk = max(1, CHUNK_SAMPLES // n)
        bounds = [(i, min(i + chunk, len(pix))) for i in range(0, len(pix), chunk)]
        sums = np.empty((len(channels), len(pix)), dtype=np.float32)

        def run(b: tuple[int, int]) -> None:
            i0, i1 = b
            ijk = [(start[i0:i1, a, None] + span[i0:i1, a, None] * frac).ravel() for a in range(3)]  # (N n,) per axis
            sums[:, i0:i1] = self._trilinear(ijk, values).reshape(len(values), i1 - i0, n).sum(-1)

        list(self._pool.map(run, bounds))
        return (sums * (chord_mm / n).astype(np.float32)).reshape(len(channels), H, W)

    def _trilinear(self, ijk: list[np.ndarray], values: list[np.ndarray]) -> np.ndarray:
        """``(C', N)`` trilinear samples at continuous indices (i, j, k: three ``(N,)`` arrays) in the box
        ``[-0.5, n - 0.5]`` (points of rays that miss the box are clamped to it; their chord, and weight, is 0).
        One contiguous array per axis and each corner gathered once: about 2x faster than one ``(N, 3)`` array."""
        flat, weights = 0, []
        for x, n, stride in zip(ijk, self.shape_ijk, (1, self._row, self._plane)):
            base = np.floor(x)
            weights.append(x - base)
            flat = flat + (np.clip(base, -1, n - 1).astype(np.int64) + 1) * stride
        fx, fy, fz = weights
        r, p = self._row, self._plane
        out = np.empty((len(values), len(flat)), dtype=np.float32)
        for c, v in enumerate(values):  # corner (di, dj, dk) is element flat of v shifted by di + dj r + dk p
            v000, v100, v010, v110, v001, v101, v011, v111 = (
                np.take(v[offset:], flat) for offset in (0, 1, r, r + 1, p, p + 1, p + r, p + r + 1))
            c00, c10, c01, c11 = (_lerp(a, b, fx) for a, b in ((v000, v100), (v010, v110), (v001, v101), (v011, v111)))
            out[c] = _lerp(_lerp(c00, c10, fy), _lerp(c01, c11, fy), fz)
        return out


def _lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``a + t (b - a)``, in ``b``'s memory (a gathered temporary)."""
    np.subtract(b, a, out=b)
    np.multiply(b, t, out=b)
    return np.add(b, a, out=b)


def _clip_to_box(s: np.ndarray, seg: np.ndarray, shape_ijk: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters ``[lo, hi]`` (fractions of source->pixel) inside ``[-0.5, n - 0.5]`` per axis."""
    inv = 1.0 / np.where(np.abs(seg) < 1e-12, 1e-12, seg)
    t0 = (-0.5 - s) * inv
    t1 = (np.asarray(shape_ijk, dtype=np.float64) - 0.5 - s) * inv
    lo = np.clip(np.minimum(t0, t1).max(axis=1), 0.0, 1.0)
    hi = np.clip(np.maximum(t0, t1).min(axis=1), 0.0, 1.0)
    return lo, np.maximum(hi, lo)
