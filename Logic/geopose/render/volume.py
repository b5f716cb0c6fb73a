"""The CTA as the renderers sample it: density channels on a pyramid of working grids.

Channel 0 is the total density (HU -> [0, 1], docs/conventions.md section 3); each
further channel is the density inside one mask (``cranium``, ``vessels``). A *level*
is the CTA grid block-averaged by a power-of-two factor per axis, cropped to the
box holding any density: a render samples the coarsest level whose voxels are no
larger than its detector pixels at the volume centre (:meth:`RenderVolume.level_for`).
A CTA finer than :data:`RENDER_GRID_MM` is rendered from its block means (:func:`render_factors`,
``register/case.py``) in its own centred frame: no render samples finer, so the levels of a 0.5 mm
512^3 CTA come from an eighth of its voxels. Levels are built on first use, slab by slab (memory
stays at a few slabs of the full grid), and cached; the density scale is fixed by the full grid,
so every level shows the same values. A render of the total density alone gets
a level without the mask channels, so the masks (the vessel mask computed from a CTA
takes seconds) are made only when a render needs them; the level then gains them, its
total channel and crop unchanged. numpy only.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import Callable, Mapping, Union

import numpy as np

from ..images import block_mean
from ..volume import Volume, index_points
from .density import DensityScale

__all__ = ["CHANNELS", "RENDER_GRID_MM", "Level", "MaskSource", "RenderVolume", "coarse_mask", "footprint_mm", "render_factors"]

#: Channel names, in order: the total density, then the density inside each mask.
CHANNELS = ("total", "cranium", "vessels")
#: Largest block factor of a level (per axis).
MAX_FACTOR = 8
#: Full-grid slices processed at once while building a level (times the level's k factor).
SLAB_SLICES = 16

#: A CTA finer than this (mm) along an axis is rendered from its block means (:func:`render_factors`): no render samples
#: a finer grid (a registration's finest level is 2 mm on a CPU, 1 mm at CUDA's 256 px: ``register/engine.py``
#: ``finest_level_mm``), and the levels and masks of a 0.5 mm 512^3 CTA are made from an eighth of its voxels.
RENDER_GRID_MM = 1.0

#: A mask: a label Volume on the CTA grid (``> 0`` inside), or a function that computes one
#: from the CTA (called once, on first use).
MaskSource = Union[Volume, Callable[[], Volume]]


def render_factors(spacing_mm: tuple[float, float, float], grid_mm: float = RENDER_GRID_MM) -> tuple[int, int, int]:
    """Block factors (i, j, k) that bring each voxel size ``spacing_mm`` up to at most ``grid_mm`` (1 where it is not
    finer): the CTA as rendered is ``cta.shrunk(render_factors(cta.spacing_mm))``."""
    return tuple(max(1, int(np.floor(grid_mm / s + 1e-6))) for s in spacing_mm)


def footprint_mm(pixel_mm: float, sdd_mm: float, source_distance_mm: float) -> float:
    """Size (mm) at ``source_distance_mm`` from the source of a ``pixel_mm`` detector pixel at ``sdd_mm``."""
    return pixel_mm * source_distance_mm / sdd_mm


@dataclass(frozen=True)
class Level:
    """One working grid: ``density`` ``(C, K, J, I)`` float32 (channels as :data:`CHANNELS`),
    ``ijk_to_world`` 4x4 from voxel index to the render frame (the CTA's centred frame, mm), the block
    ``factors`` (i, j, k) it was averaged by, the index ``origin_blocks`` (k, j, i) of its first
    block on the block grid of the whole CTA (where the crop began), and the ray-marching step (mm)."""

    density: np.ndarray
    ijk_to_world: np.ndarray
    factors: tuple[int, int, int]
    origin_blocks: tuple[int, int, int] = (0, 0, 0)

    @property
    def masked(self) -> bool:
        """Whether the mask channels were built (else ``density`` holds the total channel alone)."""
        return self.density.shape[0] == len(CHANNELS)

    @property
    def spacing_mm(self) -> tuple[float, float, float]:
        return tuple(float(v) for v in np.linalg.norm(self.ijk_to_world[:3, :3], axis=0))

    @property
    def step_mm(self) -> float:
        """Sampling step along a ray: the smallest voxel size."""
        return min(self.spacing_mm)

    @property
    def shape_ijk(self) -> tuple[int, int, int]:
        _, k, j, i = self.density.shape
        return (i, j, k)


class RenderVolume:
    """A CTA (HU) with its masks, prepared for rendering: :meth:`level` grids of density channels.

    ``masks`` maps channel names (``cranium``, ``vessels``) to a :data:`MaskSource` on the
    CTA grid; a channel without a mask is all zeros. The finest level sampled is the
    coarsest whose voxels are at most ``finest_spacing_mm`` (the CTA's own grid when None); ``scale``: the HU -> density
    map (default: the CTA's own, :class:`DensityScale`); ``centred_to_ras``: the render (world) frame, 4x4 to RAS
    (default: the CTA's centred frame; the render grid of a finer CTA keeps that CTA's, :func:`render_factors`). The CTA
    array is read, never changed.
    """

    def __init__(
        self, cta: Volume, masks: Mapping[str, MaskSource] | None = None, *, finest_spacing_mm: float | None = None,
        scale: DensityScale | None = None, centred_to_ras: np.ndarray | None = None,
    ) -> None:
        unknown = set(masks or {}) - set(CHANNELS[1:])
        if unknown:
            raise ValueError(f"unknown mask channel(s) {sorted(unknown)}; channels are {CHANNELS[1:]}")
        self.cta = cta
        self._mask_sources = dict(masks or {})
        self._masks: dict[str, np.ndarray] = {}
        self._ahead: dict[str, Future] = {}
        self._voxels: dict[str, np.ndarray] = {}
        self.finest_spacing_mm = finest_spacing_mm
        self._levels: dict[tuple[int, int, int], Level] = {}
        self._scale = scale
        self.centred_to_ras = cta.centred_to_ras if centred_to_ras is None else np.asarray(centred_to_ras, dtype=np.float64)

    @property
    def ijk_to_world(self) -> np.ndarray:
        """4x4 from CTA voxel index to the render frame (mm)."""
        return np.linalg.inv(self.centred_to_ras) @ self.cta.ijk_to_ras

    def centred_points(self, kji: np.ndarray) -> np.ndarray:
        """Voxel centres ``(N, 3)`` (render frame, mm) of CTA array indices ``kji`` ``(N, 3)`` (``[k, j, i]`` order)."""
        return index_points(kji, self.ijk_to_world)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return CHANNELS

    def mask(self, name: str) -> np.ndarray | None:
        """The ``[k, j, i]`` bool mask of channel ``name`` on the CTA grid (computed on first use, or awaited when
        :meth:`make_masks_ahead` is making it), or None."""
        if name in self._ahead:
            self._ahead[name].result()  # its error, if making it failed
        if name not in self._masks:
            source = self._mask_sources.get(name)
            if source is None:
                return None
            self._masks[name] = self._made(name, source)
        return self._masks[name]

    def _made(self, name: str, source: MaskSource) -> np.ndarray:
        vol = source() if callable(source) else source
        if vol.array.shape != self.cta.array.shape:
            raise ValueError(f"the {name} mask grid {vol.shape_ijk} differs from the CTA grid {self.cta.shape_ijk}")
        return np.asarray(vol.array) > 0

    def make_masks_ahead(self) -> None:
        """Start making the masks not yet made on another thread, so that they are ready when a render needs them
        (meanwhile the renders of the total density alone go on; the vessel mask of a 1 mm CTA takes about 2 s on 2
        cores). :meth:`mask` waits for its mask; the masks are those made on first use. The thread is no daemon: an
        interpreter that exits meanwhile waits for it (killed inside a SimpleITK filter, it printed "FATAL: exception
        not rethrown")."""
        todo = {name: Future() for name, source in self._mask_sources.items()
                if source is not None and name not in self._masks and name not in self._ahead}

        def make() -> None:
            for name, done in todo.items():
                try:
                    self._masks[name] = self._made(name, self._mask_sources[name])
                    done.set_result(None)
                except BaseException as error:  # raised again where the mask is asked for
                    done.set_exception(error)

        self._ahead |= todo
        if todo:
            threading.Thread(target=make, name="geopose-cta-masks").start()

    def mask_voxels(self, name: str) -> np.ndarray:
        """The ``[k, j, i]`` indices ``(N, 3)`` of channel ``name``'s mask voxels (none without a mask), found once."""
        if name not in self._voxels:
            mask = self.mask(name)
            self._voxels[name] = np.argwhere(mask) if mask is not None else np.zeros((0, 3), dtype=np.intp)
        return self._voxels[name]

    # ----------------------------------------------------------------- density

    @property
    def scale(self) -> DensityScale:
        """The HU -> density map (given, or the whole CTA's own, found on first use)."""
        if self._scale is None:
            self._scale = DensityScale.of(self.cta.array)
        return self._scale

    def density_slab(self, k0: int, k1: int) -> np.ndarray:
        """Total density of CTA slices ``k0:k1`` (``[k, j, i]`` float32 in [0, 1]; scale of the whole CTA)."""
        return self.scale.apply(self.cta.array[k0:k1])

    # ------------------------------------------------------------------ levels

    def factors_for(self, voxel_mm: float) -> tuple[int, int, int]:
        """Power-of-two block factors (i, j, k) giving the largest voxels no larger than ``voxel_mm``, or than
        ``finest_spacing_mm`` where that is larger, per axis."""
        bound_mm = max(voxel_mm, self.finest_spacing_mm or 0.0)
        out = []
        for s in self.cta.spacing_mm:
            f = 1
            while f * 2 <= MAX_FACTOR and f * 2 * s <= bound_mm * (1 + 1e-6):
                f *= 2
            out.append(f)
        return tuple(out)

    def level_for(self, voxel_mm: float, masked: bool = True) -> Level:
        """The coarsest level whose voxels are no larger than ``voxel_mm`` (e.g. a pixel's footprint)."""
        return self.level(self.factors_for(voxel_mm), masked)

    def level(self, factors: tuple[int, int, int] = (1, 1, 1), masked: bool = True) -> Level:
        """The level of block ``factors`` (i, j, k), built on first use; ``masked``: with the mask channels
        (else it may hold the total channel alone, :attr:`Level.masked`)."""
        factors = tuple(int(f) for f in factors)
        level = self._levels.get(factors)
        if level is None:
            level = self._levels[factors] = self._build(factors, masked)
        elif masked and not level.masked:
            level = self._levels[factors] = self._with_masks(level)
        return level

    @property
    def levels(self) -> dict[tuple[int, int, int], Level]:
        """The levels built so far."""
        return dict(self._levels)

    def _channels(self, factors: tuple[int, int, int], masked: bool, total: bool = True) -> np.ndarray:
        """Block means ``(C, K', J', I')`` of the whole grid: the total channel (``total``) and, when ``masked``,
        the density inside each mask."""
        fi, fj, fk = factors
        K = self.cta.array.shape[0]
        masks = [self.mask(name) for name in CHANNELS[1:]] if masked else []
        step = SLAB_SLICES * fk
        parts: list[list[np.ndarray]] = [[] for _ in range(int(total) + len(masks))]
        for k0 in range(0, K, step):
            k1 = min(K, k0 + step)
            dens = self.density_slab(k0, k1)
            if total:
                parts[0].append(block_mean(dens, (fk, fj, fi)))
            for c, m in enumerate(masks, start=int(total)):
                slab = dens * m[k0:k1] if m is not None else np.zeros_like(dens)
                parts[c].append(block_mean(slab, (fk, fj, fi)))
        return np.stack([np.concatenate(p, axis=0) for p in parts])

    def _with_masks(self, level: Level) -> Level:
        """``level`` with its mask channels built, on its crop."""
        (k0, j0, i0), (_, K, J, I) = level.origin_blocks, level.density.shape
        masks = self._channels(level.factors, True, total=False)[:, k0:k0 + K, j0:j0 + J, i0:i0 + I]
        return replace(level, density=np.ascontiguousarray(np.concatenate((level.density, masks))))

    def _build(self, factors: tuple[int, int, int], masked: bool = True) -> Level:
        fi, fj, fk = factors
        density = self._channels(factors, masked)
        # Crop to the box holding density (one empty voxel kept around it).
        occupied = density[0] > 0
        lo = np.zeros(3, dtype=int)
        hi = np.asarray(density.shape[1:])
        if occupied.any():
            for axis in range(3):
                keep = np.flatnonzero(occupied.any(axis=tuple(a for a in range(3) if a != axis)))
                lo[axis], hi[axis] = max(0, keep[0] - 1), min(density.shape[1 + axis], keep[-1] + 2)
        density = np.ascontiguousarray(density[:, lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
        # Index of level voxel (i, j, k) in full-grid index units: its block centre.
        scale = np.diag([fi, fj, fk, 1.0]).astype(np.float64)
        scale[:3, 3] = (np.asarray([fi, fj, fk], dtype=np.float64) - 1.0) / 2.0 + np.asarray([fi, fj, fk]) * lo[::-1]
        return Level(density, self.ijk_to_world @ scale, (fi, fj, fk), tuple(int(v) for v in lo))

    def coarsened(self, factors: tuple[int, int, int]) -> tuple["RenderVolume", np.ndarray]:
        """This CTA and its masks on the block grid of ``factors`` (i, j, k): HU block means under this CTA's density
        scale, a mask keeping the blocks it fills at least half (no copy of the full grid is made); and the ``(4, 4)``
        shift (mm) from this volume's render frame to the block grid's centred frame (a pose ``T`` here is ``shift @ T``
        there). Itself and the identity for factors of 1."""
        factors = tuple(int(f) for f in factors)
        if factors == (1, 1, 1):
            return self, np.eye(4)
        fi, fj, fk = factors
        scale = np.diag([fi, fj, fk, 1.0])
        scale[:3, 3] = (np.asarray(factors, dtype=np.float64) - 1.0) / 2.0  # block centres, in full-grid indices
        cta = Volume(_block_means(self.cta.array, factors), self.cta.ijk_to_ras @ scale, dict(self.cta.metadata))
        masks = {name: cta.like(coarse_mask(mask, factors).astype(np.uint8))
                 for name in CHANNELS[1:] if (mask := self.mask(name)) is not None}
        shift = np.eye(4)
        shift[:3, 3] = self.centred_to_ras[:3, 3] - cta.centre_ras
        return RenderVolume(cta, masks, scale=self.scale), shift

    def with_vessels(self, kept_kji: np.ndarray) -> "RenderVolume":
        """The same CTA whose vessel channel holds only the voxels ``kept_kji`` (``[k, j, i]`` indices ``(N, 3)``, unique
        and in C order as ``np.argwhere`` lists them; those outside the vessel mask are dropped): e.g. the opacified ones
        (``register/opacified.py``). The levels built so far are carried over with only their vessel channel
        recomputed (from the kept voxels alone); the CTA and the other masks are shared, never copied."""
        kji = np.asarray(kept_kji, dtype=np.intp).reshape(-1, 3)
        if len(kji) and (kji.min() < 0 or np.any(kji.max(axis=0) >= self.cta.array.shape)):
            raise ValueError(f"kept vessel voxels lie outside the CTA grid {self.cta.array.shape}")
        if np.any(np.diff(np.ravel_multi_index(tuple(kji.T), self.cta.array.shape)) <= 0):
            raise ValueError("kept vessel voxels must be unique and in C order (as np.argwhere lists them)")
        vessels = self.mask("vessels")
        kji = kji[vessels[tuple(kji.T)]] if vessels is not None else kji[:0]
        keep = np.zeros(self.cta.array.shape, dtype=bool)
        keep[tuple(kji.T)] = True
        out = RenderVolume(self.cta, finest_spacing_mm=self.finest_spacing_mm, centred_to_ras=self.centred_to_ras)
        masks = {name: mask for name in self._mask_sources if (mask := self.mask(name)) is not None}
        out._mask_sources, out._masks, out._scale = dict(self._mask_sources), masks, self.scale
        out._masks["vessels"] = keep
        out._voxels["vessels"] = kji
        values = out._scale.apply(self.cta.array[tuple(kji.T)])
        for factors, level in self._levels.items():
            if not level.masked:  # built for the total channel alone: the new volume builds its own when needed
                continue
            density = level.density.copy()
            density[CHANNELS.index("vessels")] = 0.0
            if len(kji):  # a block's mean over the full-grid voxels it holds (edge blocks hold fewer)
                f = np.asarray(factors[::-1])
                held = np.minimum(f, np.asarray(self.cta.array.shape) - (kji // f) * f).prod(axis=1)
                np.add.at(density[CHANNELS.index("vessels")], tuple((kji // f - np.asarray(level.origin_blocks)).T),
                          values / held)
            out._levels[factors] = replace(level, density=density)
        return out


def coarse_mask(mask: np.ndarray, factors: tuple[int, int, int]) -> np.ndarray:
    """The blocks of ``factors`` (i, j, k) a ``[k, j, i]`` bool mask fills at least half (the grid of
    :meth:`RenderVolume.coarsened`)."""
    return _block_means(mask, factors) >= 0.5


def _block_means(array: np.ndarray, factors: tuple[int, int, int]) -> np.ndarray:
    """:func:`block_mean` of a ``[k, j, i]`` array by ``factors`` (i, j, k), slab by slab (float32)."""
    fi, fj, fk = factors
    step = SLAB_SLICES * fk
    return np.concatenate([block_mean(array[k0:k0 + step], (fk, fj, fi)) for k0 in range(0, array.shape[0], step)])
