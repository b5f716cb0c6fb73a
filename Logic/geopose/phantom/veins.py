"""The venous side of a phantom head as centerline polylines (head coordinates, mm), and the
segments of the internal carotid artery the skull base wraps.

Dural sinuses lie against the inner table: the superior sagittal sinus over the vertex to the
torcula, the straight sinus from the vein of Galen, the transverse sinuses (one side dominant),
the sigmoid sinuses down to the jugular foramina and the internal jugular veins down the neck;
the cavernous sinuses surround the cavernous ICA. Positions are found by casting rays through
the subject's own cranial cavity, so they follow its skull.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .vessels import catmull_rom

__all__ = ["build_veins", "ica_segment", "petrous", "cavernous", "PETROUS_Z_MM", "CAVERNOUS_BOX_MM"]

#: Standard-coordinate heights (mm) of the ICA's petrous segment (in the carotid canal).
PETROUS_Z_MM = (-76.0, -51.0)
#: Standard-coordinate box (mm; |x| low/high, y low/high, z low/high) of the ICA's cavernous segment.
CAVERNOUS_BOX_MM = ((8.0, 24.0), (12.0, 31.0), (-50.0, -30.0))
#: Cavernous sinus: its radius beyond the ICA's (mm).
CAVERNOUS_MM = 3.0
#: Ray origin (standard mm) for the superior sagittal sinus, in the midsagittal plane.
SSS_ORIGIN_MM = (0.0, -5.0, -5.0)


def _inner_table(margin: Callable[[np.ndarray], np.ndarray], origin, directions: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
    """Per direction (unit rows), the last point from ``origin`` still ``depth_mm`` inside the cavity."""
    r = np.arange(5.0, 140.0, 0.5)
    pts = np.asarray(origin, float) + directions[:, None, :] * r[None, :, None]
    depth = margin(pts.reshape(-1, 3)).reshape(len(directions), len(r))
    outside = depth < np.asarray(depth_mm)[:, None]
    last = np.maximum(np.argmax(outside, axis=1) - 1, 0)
    return pts[np.arange(len(directions)), last]


def ica_segment(arteries: list[dict], side: str, scale: np.ndarray, keep: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Points (head mm) and radii of the longest run of ``ica_{side}`` whose standard-coordinate
    points satisfy ``keep(points) -> bool``; empty arrays if none."""
    for a in arteries:
        if a["name"] == f"ica_{side}":
            ok = keep(a["points"] / scale)
            edges = np.diff(np.concatenate(([0], ok.astype(np.int8), [0])))
            runs = list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))
            if runs:
                a0, b0 = max(runs, key=lambda ab: ab[1] - ab[0])
                return a["points"][a0:b0], np.asarray(a["radii"])[a0:b0]
    return np.zeros((0, 3)), np.zeros(0)


def petrous(points: np.ndarray) -> np.ndarray:
    """Bool per standard-coordinate point: at the height of the ICA's petrous segment."""
    return (points[:, 2] > PETROUS_Z_MM[0]) & (points[:, 2] < PETROUS_Z_MM[1])


def cavernous(points: np.ndarray) -> np.ndarray:
    """Bool per standard-coordinate point: inside ``CAVERNOUS_BOX_MM`` (either side)."""
    (x0, x1), (y0, y1), (z0, z1) = CAVERNOUS_BOX_MM
    ax = np.abs(points[:, 0])
    return (ax > x0) & (ax < x1) & (points[:, 1] > y0) & (points[:, 1] < y1) & (points[:, 2] > z0) & (points[:, 2] < z1)


def build_veins(scale: np.ndarray, arteries: list[dict], rng: np.random.Generator,
                margin: Callable[[np.ndarray], np.ndarray]) -> list[dict]:
    """The venous sinuses and jugular veins of a subject (``scale``: its head scale; ``arteries``:
    head mm; ``margin(pts)``: depth (mm) of standard-coordinate points inside the cranial cavity):
    dicts with ``name``, ``points`` ``(N, 3)`` head mm and ``radii`` ``(N,)`` mm."""
    veins: list[dict] = []

    def add(name, pts, radii):
        veins.append({"name": name, "points": np.asarray(pts, float) * scale, "radii": np.asarray(radii, float)})

    # superior sagittal sinus: midline over the vertex, widening backwards, down to the torcula
    theta = np.radians(np.linspace(25.0, 200.0, 36))
    r_sss = np.linspace(1.5, 4.0, len(theta)) * rng.uniform(0.85, 1.15)
    ray_ends = _inner_table(margin, SSS_ORIGIN_MM, np.stack([0 * theta, np.cos(theta), np.sin(theta)], 1), r_sss + 0.3)
    sss = catmull_rom(np.vstack([ray_ends[:-1:3], ray_ends[-1]]))
    add("superior_sagittal_sinus", sss, np.linspace(r_sss[0], r_sss[-1], len(sss)))
    torcula = sss[-1]
    # straight sinus from the vein of Galen to the torcula
    galen = np.array([0.0, -28.0, 6.0]) + rng.normal(0.0, 1.0, 3)
    straight = catmull_rom(np.array([galen, galen + (0, -8, 0), 0.5 * (galen + torcula) + (0, 0, 4), torcula]))
    add("straight_sinus", straight, np.linspace(2.0, 2.8, len(straight)))
    dominant = "right" if rng.random() < 0.6 else "left"
    for side, sx in (("left", -1.0), ("right", 1.0)):
        r_t = (4.5 if side == dominant else 3.0) * rng.uniform(0.85, 1.15)
        phi = np.radians(np.linspace(0.0, 65.0, 10))
        dirs = np.stack([sx * np.sin(phi), -np.cos(phi), -0.15 * np.sin(phi)], 1)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        transverse = _inner_table(margin, (0.0, -5.0, torcula[2]), dirs, np.full(len(phi), r_t + 0.3))
        transverse = np.vstack([torcula, transverse[1:]])
        end = transverse[-1]
        jug = np.array([35.0 * sx, -16.0, -64.0]) + rng.normal(0.0, 1.0, 3)
        ctrl = np.vstack([transverse, [end + (-3 * sx, 6, -9), (45 * sx, -24, -57), jug, (35 * sx, -11, -74),
                                      (36 * sx, -5, -95), (35 * sx, 2, -130), (34 * sx, 8, -190), (33 * sx, 10, -260)]])
        line = catmull_rom(ctrl)
        arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))))
        bulb = arc[np.argmin(np.linalg.norm(line - jug, axis=1))]
        radii = np.where(arc < bulb, r_t, np.interp(arc, [bulb, bulb + 15.0, arc[-1]], [r_t, r_t * 1.3, r_t * 1.2]))
        add(f"transverse_sigmoid_jugular_{side}", line, radii)
        pts, rad = ica_segment(arteries, side, scale, cavernous)
        if len(pts) >= 2:
            veins.append({"name": f"cavernous_sinus_{side}", "points": pts, "radii": rad + CAVERNOUS_MM})
    return veins
