"""Cone-beam DRR in numpy: the renderer of the torch-free inference path.

The same line integrals as :class:`geopose.render.DRR` (rays from the source to
every pixel, clipped to the voxel box, ``n`` midpoint samples of trilinear
density, value ``sum * step_mm``), without gradients. ``Testing/Python/test_torch_free.py``
checks it against the torch renderer.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from ..geometry.detector import Detector
from ..geometry.numpy_poses import source_and_detector_points
from ..volume import Volume
from .density import hu_to_density, label_channels

__all__ = ["NumpyDRR", "resize_bilinear"]

#: Samples (rays x steps) processed per chunk.
CHUNK_SAMPLES = 1 << 18


class NumpyDRR:
    """Render ``(C', H, W)`` line integrals (density x mm) of a ``(C, K, J, I)`` density volume.

    ``ijk_to_world`` (4x4) maps voxel indices to the centred world frame (mm); a pose
    is one camera-to-world ``(4, 4)`` matrix. ``step_mm`` defaults to the smallest voxel size.
    """

    def __init__(
        self,
        density: np.ndarray,
        ijk_to_world: np.ndarray,
        detector: Detector,
        step_mm: float | None = None,
        channel_names: Sequence[str] | None = None,
    ) -> None:
        density = np.asarray(density, dtype=np.float32)
        if density.ndim == 3:
            density = density[None]
        if density.ndim != 4:
            raise ValueError(f"density must be (K, J, I) or (C, K, J, I), got {density.shape}")
        self.channels, K, J, I = density.shape
        self.shape_ijk = (I, J, K)
        # Channel-last, zero-padded by one voxel: a trilinear corner is one flat index away.
        self._padded = np.pad(np.moveaxis(density, 0, -1), ((1, 1), (1, 1), (1, 1), (0, 0))).reshape(-1, self.channels)
        m = np.asarray(ijk_to_world, dtype=np.float64)
        self.world_to_ijk = np.linalg.inv(m)
        self.step_mm = float(step_mm) if step_mm is not None else float(np.linalg.norm(m[:3, :3], axis=0).min())
        self.detector = detector
        self.channel_names = list(channel_names) if channel_names else [f"c{i}" for i in range(self.channels)]
        row, plane = I + 2, (J + 2) * (I + 2)
        self._corners = np.array([0, 1, row, row + 1, plane, plane + 1, plane + row, plane + row + 1], dtype=np.int64)
        self._strides = np.array([1, row, plane], dtype=np.int64)

    @classmethod
    def from_volume(
        cls,
        cta: Volume,
        detector: Detector,
        labels: Volume | None = None,
        label_groups: Mapping[str, Sequence[int]] | None = None,
        step_mm: float | None = None,
    ) -> "NumpyDRR":
        """DRR of a CTA in HU; channel 0 total density, then one channel per label group."""
        density = hu_to_density(np.ascontiguousarray(cta.array, dtype=np.float32))
        stack, names = label_channels(density, None if labels is None else np.asarray(labels.array), label_groups)
        return cls(stack, cta.ijk_to_centred, detector, step_mm=step_mm, channel_names=names)

    def __call__(
        self,
        pose: np.ndarray,
        detector: Detector | None = None,
        channels: Sequence[int] | None = None,
        render_px: int | None = None,
    ) -> np.ndarray:
        """``(C', H, W)`` float32 for ``pose`` ``(4, 4)`` (or ``(1, 4, 4)``) on ``detector``.

        ``render_px``: render on the same field of view at this many pixels along the longer
        side and resize bilinearly to the detector (faster; how the networks were trained).
        """
        det = detector or self.detector
        channels = list(range(self.channels)) if channels is None else [int(c) for c in channels]
        pose = np.asarray(pose, dtype=np.float64).reshape(4, 4)
        coarse = det
        if render_px is not None and render_px < max(det.shape):
            scale = render_px / max(det.shape)
            coarse = det.resized(max(1, round(det.rows * scale)), max(1, round(det.cols * scale)))
        src, pix = source_and_detector_points(pose, coarse)
        H, W = coarse.shape
        pix = pix.reshape(-1, 3)
        s = self.world_to_ijk[:3, :3] @ src + self.world_to_ijk[:3, 3]
        d = pix @ self.world_to_ijk[:3, :3].T + self.world_to_ijk[:3, 3]
        seg = d - s
        lo, hi = _clip_to_box(s, seg, self.shape_ijk)
        chord_mm = (hi - lo) * np.linalg.norm(pix - src, axis=1)
        n = max(1, int(math.ceil(float(chord_mm.max()) / self.step_mm)))
        frac = (np.arange(n) + 0.5) / n
        start = s + lo[:, None] * seg
        span = (hi - lo)[:, None] * seg
        sums = np.empty((len(pix), len(channels)), dtype=np.float64)
        chunk = max(1, CHUNK_SAMPLES // n)
        for i in range(0, len(pix), chunk):
            pts = start[i : i + chunk, None, :] + span[i : i + chunk, None, :] * frac[:, None]  # (N, n, 3) ijk
            sums[i : i + chunk] = self._trilinear(pts.reshape(-1, 3), channels).reshape(-1, n, len(channels)).sum(1)
        image = (sums * (chord_mm / n)[:, None]).T.reshape(len(channels), H, W).astype(np.float32)
        return image if coarse is det else resize_bilinear(image, det.shape)

    def _trilinear(self, ijk: np.ndarray, channels: list[int]) -> np.ndarray:
        """``(N, C')`` trilinear samples at continuous indices ``(N, 3)`` in the box ``[-0.5, n - 0.5]``
        (points of rays that miss the box are clamped to it; their chord, and weight, is 0)."""
        base = np.floor(ijk)
        f = (ijk - base).astype(np.float32)
        base = np.clip(base, -1, np.asarray(self.shape_ijk) - 1)
        flat = (base.astype(np.int64) + 1) @ self._strides
        out = np.zeros((len(ijk), len(channels)), dtype=np.float32)
        values = self._padded[:, channels] if len(channels) < self.channels else self._padded
        for c, offset in enumerate(self._corners):
            w = np.where(c & 1, f[:, 0], 1 - f[:, 0]) * np.where(c & 2, f[:, 1], 1 - f[:, 1]) * np.where(c & 4, f[:, 2], 1 - f[:, 2])
            out += values[flat + offset] * w[:, None]
        return out


def _clip_to_box(s: np.ndarray, seg: np.ndarray, shape_ijk: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters ``[lo, hi]`` (fractions of source->pixel) inside ``[-0.5, n - 0.5]`` per axis."""
    inv = 1.0 / np.where(np.abs(seg) < 1e-12, 1e-12, seg)
    t0 = (-0.5 - s) * inv
    t1 = (np.asarray(shape_ijk, dtype=np.float64) - 0.5 - s) * inv
    lo = np.clip(np.minimum(t0, t1).max(axis=1), 0.0, 1.0)
    hi = np.clip(np.maximum(t0, t1).min(axis=1), 0.0, 1.0)
    return lo, np.maximum(hi, lo)


def resize_bilinear(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(C, h, w)`` -> ``(C, H, W)``, bilinear with pixel-centre alignment (torch's
    ``interpolate(mode="bilinear", align_corners=False)``)."""
    _, h, w = image.shape
    H, W = shape

    def axis(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.clip((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0, None)
        i0 = np.minimum(np.floor(x).astype(np.int64), n_in - 1)
        return i0, np.minimum(i0 + 1, n_in - 1), (x - i0).astype(np.float32)

    r0, r1, fr = axis(h, H)
    c0, c1, fc = axis(w, W)
    rows = image[:, r0] * (1 - fr)[:, None] + image[:, r1] * fr[:, None]
    return (rows[:, :, c0] * (1 - fc) + rows[:, :, c1] * fc).astype(np.float32)
