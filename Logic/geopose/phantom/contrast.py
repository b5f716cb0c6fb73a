"""How a phantom CTA shows its tissues beyond their shapes: the arterial contrast along the tree,
calcified plaques, the scanner's noise and streaks.

All of it is drawn from the subject's own stream ``[seed, ENHANCEMENT_STREAM]``, so that the draws
of the head, its arteries and the poses (the subject's main stream) stay what they were.
Positions are head coordinates (mm, ``anatomy``); values are HU.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from .raster import Grid, SmoothField
from .vessels import path_length_mm

__all__ = [
    "ENHANCEMENT_STREAM", "ARTERIAL_HU_RANGE", "Enhancement", "sample_enhancement", "lumen_hu", "correlated_noise",
    "add_streaks",
]

#: Second key of the subject's appearance stream ``np.random.default_rng([seed, ENHANCEMENT_STREAM])``.
ENHANCEMENT_STREAM = 30
#: Lumen HU every arterial point is kept within.
ARTERIAL_HU_RANGE = (150.0, 600.0)
#: Path length (mm) from the neck at which the lumen has fallen to the subject's distal share.
DISTAL_PATH_MM = 450.0
#: Correlation length (mm) of the smooth variation of the lumen HU (a 3D field sampled on the tree).
VARIATION_CELL_MM = 30.0
#: Chance of a calcified plaque at each site (carotid bulb and siphon, per side), its HU and radius (mm).
PLAQUE_PROBABILITY = 0.35
PLAQUE_HU = (600.0, 1500.0)
PLAQUE_RADIUS_MM = (0.8, 1.8)
#: Head-frame sources (standard mm, before the head's scale) of streaks: the teeth, the petrous bones.
STREAK_SOURCES_MM = ((0.0, 50.0, -95.0), (-40.0, -16.0, -46.0), (40.0, -16.0, -46.0))
#: Streaks fade over this distance (mm) above and below their source's slice.
STREAK_HALF_SLAB_MM = 6.0


@dataclass
class Enhancement:
    """One subject's appearance draws (HU, mm; head coordinates).

    ``distal_share``: lumen HU at ``DISTAL_PATH_MM`` along the tree as a share of the proximal
    (common carotid) HU; ``asymmetry``: share by which the right side's bolus exceeds the left's;
    ``variation``: sd (share) of the smooth variation along the vessels; ``dura_hu``: the enhancing
    dura; ``noise_neighbour_weight``: the noise's spatial correlation (``correlated_noise``);
    ``plaques``: ``site``, ``side``, ``centre_mm``, ``radius_mm``, ``hu``; ``streaks``:
    ``source_mm``, ``angle_rad`` (in the axial slice), ``amplitude_hu`` (signed), ``width_mm``,
    ``length_mm``."""

    distal_share: float
    asymmetry: float
    variation: float
    dura_hu: float
    noise_neighbour_weight: float
    plaques: list[dict] = field(default_factory=list)
    streaks: list[dict] = field(default_factory=list)

    @property
    def record(self) -> dict:
        """JSON-ready."""
        return {
            "distal_share": self.distal_share, "distal_path_mm": DISTAL_PATH_MM, "asymmetry": self.asymmetry,
            "variation": self.variation, "dura_hu": self.dura_hu, "noise_neighbour_weight": self.noise_neighbour_weight,
            "plaques": [{k: (np.round(v, 3).tolist() if isinstance(v, np.ndarray) else v) for k, v in q.items()} for q in self.plaques],
            "streaks": len(self.streaks),
        }


def _plaque_sites(arteries: list[dict]) -> list[tuple[str, str, np.ndarray, float, np.ndarray]]:
    """(site, side, point, lumen radius, tangent) of the carotid bulb (8 mm up the ICA) and of the
    siphon's anterior knee (the most anterior point of the ICA's last third), per side."""
    sites = []
    for a in arteries:
        if a["name"] not in ("ica_left", "ica_right"):
            continue
        pts, side = a["points"], a["name"].split("_")[1]
        arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))))
        bulb = int(np.searchsorted(arc, 8.0))
        tail = 2 * len(pts) // 3
        knee = tail + int(np.argmax(pts[tail:, 1]))
        for site, k in (("bifurcation", bulb), ("siphon", knee)):
            k = min(max(k, 1), len(pts) - 2)
            t = pts[k + 1] - pts[k - 1]
            sites.append((site, side, pts[k], float(a["radii"][k]), t / np.linalg.norm(t)))
    return sites


def sample_enhancement(rng: np.random.Generator, arteries: list[dict]) -> Enhancement:
    """Draw one subject's appearance (see :class:`Enhancement`) given its arteries (head mm)."""
    e = Enhancement(
        distal_share=float(rng.uniform(0.55, 0.9)),
        asymmetry=float(rng.normal(0.0, 0.05)),
        variation=float(rng.uniform(0.03, 0.1)),
        dura_hu=float(rng.uniform(55.0, 100.0)),
        noise_neighbour_weight=float(rng.uniform(0.15, 0.5)),
    )
    for site, side, point, radius, tangent in _plaque_sites(arteries):
        if rng.random() >= PLAQUE_PROBABILITY:
            continue
        normal = np.cross(tangent, rng.normal(size=3))
        normal /= np.linalg.norm(normal)
        e.plaques.append({"site": site, "side": side, "centre_mm": point + 0.9 * radius * normal,
                          "radius_mm": float(rng.uniform(*PLAQUE_RADIUS_MM)), "hu": float(rng.uniform(*PLAQUE_HU))})
    sign = 1.0
    for source in STREAK_SOURCES_MM:
        for _ in range(int(rng.integers(1, 4))):
            sign = -sign
            e.streaks.append({"source_mm": np.asarray(source), "angle_rad": float(rng.uniform(0.0, np.pi)),
                              "amplitude_hu": sign * float(rng.uniform(10.0, 35.0)), "width_mm": float(rng.uniform(0.6, 1.2)),
                              "length_mm": float(rng.uniform(50.0, 120.0))})
    return e


def lumen_hu(arteries: list[dict], proximal_hu: float, e: Enhancement, rng: np.random.Generator) -> list[np.ndarray]:
    """Per artery, the lumen HU at each point: ``proximal_hu`` at the neck, falling smoothly with the
    path length along the tree (``vessels.path_length_mm``) to ``e.distal_share`` of it at
    ``DISTAL_PATH_MM`` and beyond, brighter on one side by ``e.asymmetry``, times a smooth random
    variation (a 3D field, so vessels that meet agree), kept within ``ARTERIAL_HU_RANGE``."""
    p = np.concatenate([a["points"] for a in arteries]).astype(np.float32)
    x = np.clip(np.concatenate(path_length_mm(arteries)) / DISTAL_PATH_MM, 0.0, 1.0)
    fall = 1.0 - (1.0 - e.distal_share) * x * x * (3.0 - 2.0 * x)
    wobble = 1.0 + e.variation * SmoothField(rng, VARIATION_CELL_MM)(p[:, 0], p[:, 1], p[:, 2])
    side = 1.0 + e.asymmetry * np.tanh(p[:, 0] / 20.0)
    hu = np.clip(proximal_hu * fall * side * wobble, *ARTERIAL_HU_RANGE)
    return np.split(hu, np.cumsum([len(a["points"]) for a in arteries])[:-1])


def correlated_noise(white: np.ndarray, neighbour_weight: float) -> np.ndarray:
    """Unit-variance noise, spatially correlated: ``white`` (float32, unit variance) filtered along
    each axis by the kernel ``[w, 1, w]`` (``w = neighbour_weight``; 0.5 gives a correlation of
    about 0.7 voxel sd) and rescaled to unit variance."""
    x = white
    w = np.float32(neighbour_weight)
    for axis in range(3):
        lo = tuple(slice(None, -1) if d == axis else slice(None) for d in range(3))
        hi = tuple(slice(1, None) if d == axis else slice(None) for d in range(3))
        y = x.copy()
        y[hi] += w * x[lo]
        y[lo] += w * x[hi]
        x = y
    return x / np.float32((1.0 + 2.0 * neighbour_weight**2) ** 1.5)


def add_streaks(hu: np.ndarray, grid: Grid, scale: np.ndarray, streaks: list[dict]) -> None:
    """Add faint straight streaks (in place) to the axial slices (the grid's k planes) near each
    streak's source: a line through the source, Gaussian across (``width_mm``), fading along it
    (``length_mm``) and over ``STREAK_HALF_SLAB_MM`` above and below."""
    K, J, I = hu.shape
    sp = np.linalg.norm(grid.ijk_to_head[:3, :3], axis=0)
    di = (np.arange(I, dtype=np.float32) * sp[0])[None, :]
    dj = (np.arange(J, dtype=np.float32) * sp[1])[:, None]
    for s in streaks:
        i0, j0, k0 = (grid.head_to_ijk @ np.append(np.asarray(s["source_mm"]) * scale, 1.0))[:3]
        k = np.arange(max(0, int(np.floor(k0 - STREAK_HALF_SLAB_MM / sp[2]))), min(K, int(np.ceil(k0 + STREAK_HALF_SLAB_MM / sp[2])) + 1))
        if k.size == 0:
            continue
        slab = np.clip(1.0 - np.abs(k - k0) * sp[2] / STREAK_HALF_SLAB_MM, 0.0, None).astype(np.float32)
        c, n = np.float32(np.cos(s["angle_rad"])), np.float32(np.sin(s["angle_rad"]))
        x, y = di - np.float32(i0 * sp[0]), dj - np.float32(j0 * sp[1])
        along, across = x * c + y * n, -x * n + y * c
        line = np.float32(s["amplitude_hu"]) * np.exp(-0.5 * (across / np.float32(s["width_mm"])) ** 2 - np.abs(along) / np.float32(s["length_mm"]))
        hu[k] += slab[:, None, None] * line[None]
