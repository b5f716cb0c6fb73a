"""An arteriovenous malformation (AVM) for a phantom subject drawn with ``pathology="avm"``.

A compact nidus (a tangle of small tortuous vessels in a ball of 8-14 mm radius, deep in one
MCA territory) fed by an enlarged branch of the superior M2 trunk and drained early by an enlarged
vein into the superior sagittal sinus. Drawn from the subject's stream ``[seed, AVM_STREAM]``, so
the subject's other draws stay what they were. Head coordinates (mm, ``anatomy``).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from . import labels as L
from .vessels import catmull_rom

__all__ = ["AVM_STREAM", "PATHOLOGIES", "build_avm", "add_drainage"]

#: Second key of the AVM's stream ``np.random.default_rng([seed, AVM_STREAM])``.
AVM_STREAM = 31
#: The pathologies a phantom subject can be drawn with.
PATHOLOGIES = ("avm",)
#: Nidus ball radius (mm), number of tangled vessels and their radius (mm).
NIDUS_RADIUS_MM = (8.0, 14.0)
NIDUS_VESSELS = (60, 100)
NIDUS_VESSEL_RADIUS_MM = (0.6, 1.2)
#: Depth (mm) of the nidus ball's surface below the cortex (the cavity's edge).
NIDUS_DEPTH_MM = 6.0


def build_avm(arteries: list[dict], scale: np.ndarray, rng: np.random.Generator,
              margin: Callable[[np.ndarray], np.ndarray]) -> dict:
    """The nidus and its feeder for a subject with ``arteries`` (head mm) and head ``scale``
    (``margin(pts)``: depth in mm of standard-coordinate points inside the cranial cavity): a dict with
    ``side``, ``centre_mm``, ``radius_mm``, ``feeder`` (an artery dict: ``name``, ``label``, ``points``,
    ``radii``) and ``nidus`` (tube dicts: ``points``, ``radii``)."""
    side = "left" if rng.random() < 0.5 else "right"
    trunk = next(a["points"] for a in arteries if a["name"] == f"m2_sup_{side}")
    origin = trunk[int(rng.uniform(0.4, 0.8) * (len(trunk) - 1))]
    radius = float(rng.uniform(*NIDUS_RADIUS_MM))
    inward = -origin / np.linalg.norm(origin)
    depth = np.arange(0.0, 60.0, 1.0)
    along = origin + depth[:, None] * inward
    deep_enough = margin(along / scale) >= radius + NIDUS_DEPTH_MM
    centre = along[int(np.argmax(deep_enough))] + rng.normal(0.0, 2.0, 3)
    # the feeder: an enlarged branch from the M2 trunk into the ball
    mid = 0.5 * (origin + centre) + rng.normal(0.0, 3.0, 3)
    entry = centre + radius * (origin - centre) / np.linalg.norm(origin - centre)
    feeder = catmull_rom(np.array([origin, mid, entry, centre]))
    label = L.ANTERIOR_LEFT if side == "left" else L.ANTERIOR_RIGHT
    nidus = []
    for _ in range(int(rng.integers(*NIDUS_VESSELS))):
        pos = centre + _in_ball(rng, 0.8 * radius)
        d = rng.normal(size=3)
        pts = [pos.copy()]
        for _ in range(int(rng.integers(4, 8))):
            d = d / np.linalg.norm(d) + 0.8 * rng.normal(size=3)
            if np.linalg.norm(pos - centre) > 0.8 * radius:
                d += 1.5 * (centre - pos) / np.linalg.norm(centre - pos)
            pos = pos + 2.5 * d / np.linalg.norm(d)
            pts.append(pos.copy())
        line = catmull_rom(np.array(pts))
        nidus.append({"points": line, "radii": np.full(len(line), rng.uniform(*NIDUS_VESSEL_RADIUS_MM))})
    return {
        "side": side, "centre_mm": centre, "radius_mm": radius,
        "feeder": {"name": f"avm_feeder_{side}", "label": label, "points": feeder, "radii": np.linspace(1.5, 1.2, len(feeder))},
        "nidus": nidus,
    }


def _in_ball(rng: np.random.Generator, radius: float) -> np.ndarray:
    v = rng.normal(size=3)
    return radius * rng.random() ** (1.0 / 3.0) * v / np.linalg.norm(v)


def add_drainage(avm: dict, veins: list[dict], scale: np.ndarray, rng: np.random.Generator,
                 margin: Callable[[np.ndarray], np.ndarray]) -> None:
    """Add ``avm["drain"]`` (``points``, ``radii``; head mm): an enlarged vein from the nidus up to the
    cortex and along it into the nearest point of the superior sagittal sinus."""
    sss = next(v["points"] for v in veins if v["name"] == "superior_sagittal_sinus")
    centre, radius = avm["centre_mm"], avm["radius_mm"]
    target = sss[int(np.argmin(np.linalg.norm(sss - centre, axis=1)))]
    outward = centre / np.linalg.norm(centre)
    r = np.arange(0.0, 80.0, 1.0)
    ray = centre + r[:, None] * outward
    cortex = ray[int(np.argmax(margin(ray / scale) < 4.0))]
    exit_ = centre + radius * (cortex - centre) / np.linalg.norm(cortex - centre)
    over = 0.5 * (cortex + target) + rng.normal(0.0, 3.0, 3)
    shrink = np.linspace(1.3, 0.5, 81)[:, None] * over  # onto the brain surface, 4 mm inside
    over = shrink[int(np.argmax(margin(shrink / scale) >= 4.0))]
    line = catmull_rom(np.array([centre, exit_, cortex, over, target]))
    avm["drain"] = {"points": line, "radii": np.linspace(1.5, rng.uniform(2.0, 3.0), len(line))}
