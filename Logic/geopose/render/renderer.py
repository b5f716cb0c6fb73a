"""One renderer interface over two kernels: ``make_renderer(volume, engine="numpy" | "torch")``.

A :class:`Renderer` renders line integrals (density x mm, docs/conventions.md section 3)
of a :class:`~geopose.render.volume.RenderVolume` for camera-to-world poses in the
centred CTA frame (float64 ``(4, 4)`` or ``(B, 4, 4)``, mm) on a detector, for the
channels asked for by name; numpy in, numpy out, whichever kernel. Everything but the
ray-marching kernel is written once here: channel names, the level each render samples
(the coarsest grid no finer than the rendered pixel's footprint at the volume centre),
rendering at ``render_px`` and resizing as the networks were trained. The kernels are
:class:`~geopose.render.numpy_drr.NumpyKernel` (no PyTorch) and the differentiable
:class:`~geopose.render.drr.DRR` (PyTorch; the test-time optimisation uses its gradients).
"""

from __future__ import annotations

import copy
from typing import Sequence

import numpy as np

from ..geometry.detector import Detector
from ..images import resize_bilinear
from .volume import CHANNELS, Level, RenderVolume, footprint_mm

__all__ = ["ENGINES", "Renderer", "NumpyRenderer", "TorchRenderer", "make_renderer", "coarse_detector"]

#: Rendering kernels.
ENGINES = ("numpy", "torch")
#: Largest voxel of the sampled level, in pixel footprints at the volume centre: the images
#: compared (MAPs resampled with anti-aliasing, then bilateral-filtered; min-max DRRs for the
#: networks) hold no detail at a pixel's own scale.
VOXEL_PER_PIXEL = 1.5


def coarse_detector(detector: Detector, render_px: int | None) -> Detector:
    """The same field of view on ``render_px`` pixels along the longer side (unchanged when None or not smaller)."""
    if render_px is None or render_px >= max(detector.shape):
        return detector
    scale = render_px / max(detector.shape)
    return detector.resized(max(1, round(detector.rows * scale)), max(1, round(detector.cols * scale)))


class Renderer:
    """Renders ``volume`` (see the module doc); subclasses supply :meth:`_render_level`.
    ``voxel_per_pixel``: a render samples the coarsest level whose voxels are at most this
    many of its pixels' footprints at the volume centre."""

    engine = ""
    voxel_per_pixel = VOXEL_PER_PIXEL

    def __init__(self, volume: RenderVolume) -> None:
        self.volume = volume

    def sampling(self, voxel_per_pixel: float) -> "Renderer":
        """This renderer (its volume and kernels shared) sampling the coarsest level whose voxels are at most
        ``voxel_per_pixel`` of its pixels' footprints."""
        out = copy.copy(self)
        out.voxel_per_pixel = float(voxel_per_pixel)
        return out

    @staticmethod
    def channel_index(channels: Sequence[str]) -> tuple[int, ...]:
        """Indices of channel names (``total``, ``cranium``, ``vessels``)."""
        unknown = [c for c in channels if c not in CHANNELS]
        if unknown:
            raise ValueError(f"unknown render channel(s) {unknown}; channels are {CHANNELS}")
        return tuple(CHANNELS.index(c) for c in channels)

    def level_for_pose(self, pose: np.ndarray, detector: Detector, masked: bool = True) -> Level:
        """The level a render of ``pose`` (``(4, 4)`` or the first of a batch) on ``detector`` samples
        (``masked``: with the mask channels)."""
        source_mm = float(np.linalg.norm(np.asarray(pose, dtype=np.float64).reshape(-1, 4, 4)[0, :3, 3]))
        pixel_mm = footprint_mm(min(detector.spacing_mm), detector.sdd_mm, max(source_mm, 1.0))
        return self.volume.level_for(pixel_mm * self.voxel_per_pixel, masked)

    def render(
        self,
        pose: np.ndarray,
        detector: Detector,
        channels: Sequence[str] = ("total",),
        *,
        render_px: int | None = None,
    ) -> np.ndarray:
        """Line integrals (density x mm), float32: ``(C, H, W)`` for one pose ``(4, 4)``, ``(B, C, H, W)``
        for ``(B, 4, 4)``. ``render_px``: render on that many pixels along the detector's longer side
        and resize bilinearly to ``detector`` (how the networks' images were made)."""
        poses = np.asarray(pose, dtype=np.float64)
        single = poses.shape == (4, 4)
        poses = poses.reshape(-1, 4, 4)
        coarse = coarse_detector(detector, render_px)
        indices = self.channel_index(channels)
        level = self.level_for_pose(poses, coarse, masked=any(indices))
        image = self._render_level(level, poses, coarse, indices)
        if coarse is not detector:
            image = np.stack([resize_bilinear(im, detector.shape) for im in image])
        return image[0] if single else image

    def _render_level(self, level: Level, poses: np.ndarray, detector: Detector, channels: tuple[int, ...]) -> np.ndarray:
        """``(B, C', H, W)`` float32 line integrals of ``level`` for ``poses`` ``(B, 4, 4)``."""
        raise NotImplementedError


class NumpyRenderer(Renderer):
    """The numpy kernel (no PyTorch): :class:`~geopose.render.numpy_drr.NumpyKernel` per level."""

    engine = "numpy"

    def __init__(self, volume: RenderVolume) -> None:
        super().__init__(volume)
        self._kernels: dict = {}

    def _render_level(self, level: Level, poses: np.ndarray, detector: Detector, channels: tuple[int, ...]) -> np.ndarray:
        from .numpy_drr import NumpyKernel

        key = (level.factors, level.masked)
        kernel = self._kernels.get(key)
        if kernel is None:
            if level.masked:  # the level gained its masks: its total-only kernel is not used again
                self._kernels.pop((level.factors, False), None)
            kernel = self._kernels[key] = NumpyKernel(level.density, level.ijk_to_world, level.step_mm)
        return np.stack([kernel(p, detector, channels) for p in poses])


class TorchRenderer(Renderer):
    """The torch kernel: a differentiable :class:`~geopose.render.drr.DRR` per level on ``device``."""

    engine = "torch"

    def __init__(self, volume: RenderVolume, device: str = "cpu") -> None:
        super().__init__(volume)
        import torch

        self.device = torch.device(device)
        self._drrs: dict = {}

    def drr(self, level: Level):
        """The torch DRR module of ``level`` (for differentiable renders)."""
        key = (level.factors, level.masked)
        drr = self._drrs.get(key)
        if drr is None:
            import torch

            from .drr import DRR

            if level.masked:  # the level gained its masks: its total-only module is not used again
                self._drrs.pop((level.factors, False), None)
            density = torch.as_tensor(level.density, device=self.device)
            drr = self._drrs[key] = DRR(density, level.ijk_to_world, Detector.model(), step_mm=level.step_mm,
                                        channel_names=CHANNELS[:level.density.shape[0]]).to(self.device)
        return drr

    def _render_level(self, level: Level, poses: np.ndarray, detector: Detector, channels: tuple[int, ...]) -> np.ndarray:
        import torch

        with torch.no_grad():
            pose = torch.as_tensor(poses, dtype=torch.float64, device=self.device)
            return self.drr(level)(pose, detector=detector, channels=channels).cpu().numpy()


def make_renderer(volume: RenderVolume, engine: str = "numpy", device: str = "cpu") -> Renderer:
    """The renderer of ``volume`` on ``engine`` (``numpy`` or ``torch``; ``device`` for torch)."""
    if engine == "numpy":
        return NumpyRenderer(volume)
    if engine == "torch":
        return TorchRenderer(volume, device)
    raise ValueError(f"render engine must be one of {ENGINES}, got {engine!r}")
