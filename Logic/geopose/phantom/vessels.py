"""The arterial tree of a phantom subject as centerline polylines (head coordinates, mm).

Major arteries come from landmark templates (cervical, petrous and cavernous ICA
with the siphon, ECA branches, vertebral arteries joining into the basilar, the
Circle of Willis with its variants) perturbed per subject; the ACA, MCA and PCA
territories get random cortical branches that follow the brain surface. Radii
taper along each vessel.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from . import labels as L

__all__ = ["build_arteries", "catmull_rom", "path_length_mm"]

#: Point spacing (mm) of the output centerlines.
CENTERLINE_STEP_MM = 1.0


def catmull_rom(ctrl: np.ndarray, step_mm: float = CENTERLINE_STEP_MM) -> np.ndarray:
    """A smooth curve through control points ``(N, 3)``, sampled about every ``step_mm``."""
    ctrl = np.asarray(ctrl, float)
    if len(ctrl) < 2:
        raise ValueError("a centerline needs at least two control points")
    p = np.vstack([2 * ctrl[0] - ctrl[1], ctrl, 2 * ctrl[-1] - ctrl[-2]])
    out = [ctrl[:1]]
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        n = max(2, int(np.ceil(np.linalg.norm(p2 - p1) / step_mm)))
        t = np.linspace(0, 1, n + 1)[1:, None]
        seg = 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3)
        out.append(seg)
    return np.vstack(out)


def _taper(n: int, r0: float, r1: float) -> np.ndarray:
    return np.linspace(r0, r1, n)


def build_arteries(p, rng: np.random.Generator, margin: Callable[[np.ndarray], np.ndarray]) -> list[dict]:
    """Arteries of subject ``p`` (a ``HeadParams``): dicts with ``name``, ``label``,
    ``points`` ``(N, 3)`` head mm and ``radii`` ``(N,)`` mm. ``margin(pts)`` is the depth
    (mm) of standard-coordinate points inside the cranial cavity."""
    tort = p.tortuosity_mm
    cow = p.cow
    arteries: list[dict] = []

    def jitter(pts, sd):
        pts = np.array(pts, float)
        if len(pts) > 2:
            pts[1:-1] += rng.normal(0.0, sd, (len(pts) - 2, 3))
        return pts

    def add(name, label, ctrl, r0, r1, sd=None):
        if r0 <= 0:
            return None
        pts = catmull_rom(jitter(ctrl, tort if sd is None else sd))
        arteries.append({"name": name, "label": label, "points": pts, "radii": _taper(len(pts), r0, r1)})
        return pts

    # Shared landmarks, perturbed once so that the vessels meeting there stay joined.
    node = {
        "ba_low": np.array([0.0, 4.0, -50.0]) + rng.normal(0, 1.5, 3),
        "ba_top": np.array([0.0, 9.0, -22.0]) + rng.normal(0, 1.5, 3),
    }
    for side, sx in (("left", -1.0), ("right", 1.0)):
        node[f"bif_{side}"] = np.array([25 * sx, 15.0, -128.0]) + rng.normal(0, 4.0, 3)
        node[f"term_{side}"] = np.array([14 * sx, 16.0, -18.0]) + rng.normal(0, 1.5, 3)
        node[f"p1p2_{side}"] = np.array([12 * sx, 4.0, -21.0]) + rng.normal(0, 1.0, 3)
        node[f"acom_{side}"] = np.array([2.0 * sx, 30.0, -12.0]) + rng.normal(0, 1.0, 3)
        node[f"mbif_{side}"] = np.array([40 * sx, 15.0, -12.0]) + rng.normal(0, 2.5, 3)

    for side, sx in (("left", -1.0), ("right", 1.0)):
        ica = L.ICA_LEFT if side == "left" else L.ICA_RIGHT
        ant = L.ANTERIOR_LEFT if side == "left" else L.ANTERIOR_RIGHT
        ext = L.EXTERNAL_LEFT if side == "left" else L.EXTERNAL_RIGHT
        b, term = node[f"bif_{side}"], node[f"term_{side}"]
        add(f"cca_{side}", ext, [(22 * sx, 14, -260), (23 * sx, 14, -190), b], 3.4, 3.2, sd=2.0)
        loop = rng.normal(0, 2.0 * tort, 3)
        add(
            f"ica_{side}", ica,
            [b, (27 * sx, 9, -112) + loop, (28 * sx, 5, -92) - loop, (26 * sx, 2, -74), (25 * sx, 3, -58),
             (22 * sx, 9, -52), (17 * sx, 16, -49), (15 * sx, 19, -44), (15 * sx, 21, -37), (16 * sx, 28, -35),
             (16 * sx, 32, -29), (15 * sx, 27, -23), term],
            2.5, 1.9, sd=0.6 * tort,
        )
        # external carotid and its branches
        e_top = add(f"eca_{side}", ext, [b, (30 * sx, 22, -116), (34 * sx, 20, -96), (40 * sx, 14, -80), (48 * sx, 8, -66)], 2.0, 1.4)
        add(f"facial_{side}", ext, [e_top[8], (38 * sx, 42, -124), (44 * sx, 60, -108), (36 * sx, 74, -80), (24 * sx, 82, -58)], 1.3, 0.8)
        add(f"lingual_{side}", ext, [e_top[4], (22 * sx, 38, -110), (12 * sx, 58, -104)], 1.1, 0.7)
        add(f"occipital_{side}", ext, [e_top[6], (36 * sx, -10, -104), (42 * sx, -45, -80), (38 * sx, -78, -44), (28 * sx, -92, -10)], 1.2, 0.7)
        sta = add(f"sup_temporal_{side}", ext, [e_top[-1], (60 * sx, 10, -50), (76 * sx, 14, -20), (80 * sx, 20, 15), (72 * sx, 34, 50)], 1.2, 0.7)
        add(f"sup_temporal_parietal_{side}", ext, [sta[len(sta) // 2], (80 * sx, -5, 10), (74 * sx, -25, 45), (58 * sx, -35, 72)], 0.9, 0.6)
        maxi = add(f"maxillary_{side}", ext, [e_top[2 * len(e_top) // 3], (36 * sx, 22, -74), (28 * sx, 36, -66), (18 * sx, 46, -58)], 1.2, 0.8)
        add(f"middle_meningeal_{side}", ext, [maxi[5], (30 * sx, 8, -54), (52 * sx, 12, -36), (64 * sx, 4, 0), (58 * sx, -12, 40)], 0.9, 0.6)

        # vertebral artery through the transverse foramina, C1 loop, foramen magnum
        va_r = cow[f"va_{side}"]
        add(
            f"vertebral_{side}", L.POSTERIOR,
            [(30 * sx, -4, -260), (26 * sx, -8, -190), (24 * sx, -12, -140), (24 * sx, -12, -100), (26 * sx, -14, -86),
             (30 * sx, -20, -78), (28 * sx, -32, -74), (14 * sx, -32, -70), (10 * sx, -18, -62), (5 * sx, -4, -55), node["ba_low"]],
            va_r, 0.85 * va_r, sd=1.0,
        )
        add(f"pica_{side}", L.POSTERIOR, [(10 * sx, -18, -62), (18 * sx, -34, -58), (12 * sx, -48, -48), (20 * sx, -62, -40)], 0.8, 0.5)
        add(f"sca_{side}", L.POSTERIOR, [node["ba_top"] + (0, 0, -4), (14 * sx, 2, -28), (24 * sx, -22, -30), (14 * sx, -48, -30)], 0.9, 0.5)

        # Circle of Willis: PComm, P1 (small when the PCA is fetal), A1
        pcomm = cow[f"pcomm_{side}"]
        fetal = pcomm >= 1.3
        add(f"pcomm_{side}", ant, [term, term + (0.5 * sx, -6, -2), node[f"p1p2_{side}"]], 0.8 * pcomm, 0.8 * pcomm, sd=0.5)
        add(f"p1_{side}", L.POSTERIOR, [node["ba_top"], (7 * sx, 8, -22), node[f"p1p2_{side}"]], 0.5 if fetal else 1.2, 0.5 if fetal else 1.1, sd=0.3)
        pca = add(
            f"pca_{side}", L.POSTERIOR,
            [node[f"p1p2_{side}"], (22 * sx, -6, -16), (28 * sx, -26, -10), (22 * sx, -50, -2), (14 * sx, -74, 6), (8 * sx, -86, 12)],
            1.2, 0.8,
        )
        add(f"a1_{side}", ant, [term, (8 * sx, 24, -14), node[f"acom_{side}"]], cow[f"a1_{side}"], cow[f"a1_{side}"], sd=0.5)
        aca = add(
            f"aca_{side}", ant,
            [node[f"acom_{side}"], (3 * sx, 40, 0), (3 * sx, 44, 16), (3 * sx, 28, 30), (3 * sx, 2, 35), (3 * sx, -26, 32), (3 * sx, -42, 22)],
            1.1, 0.7, sd=1.0,
        )
        add(f"callosomarginal_{side}", ant, [aca[len(aca) // 3], (4 * sx, 52, 26), (4 * sx, 36, 50), (4 * sx, 8, 60), (4 * sx, -20, 58)], 0.9, 0.6, sd=1.5)
        # middle cerebral: M1 to the bifurcation, two M2 trunks through the insula
        mb = node[f"mbif_{side}"]
        add(f"m1_{side}", ant, [term, (24 * sx, 18, -17), (34 * sx, 17, -15), mb], 1.5, 1.3, sd=1.0)
        m2a = add(f"m2_sup_{side}", ant, [mb, (46 * sx, 12, -2), (44 * sx, 0, 12), (54 * sx, -12, 32)], 1.1, 0.9, sd=2.0)
        m2b = add(f"m2_inf_{side}", ant, [mb, (48 * sx, 5, -16), (50 * sx, -16, -10), (56 * sx, -36, 2)], 1.1, 0.9, sd=2.0)
        for trunk, count in ((m2a, 5), (m2b, 5), (aca, 4), (pca, 4)):
            lab = L.POSTERIOR if trunk is pca else ant
            for k in range(count):
                start = trunk[int(rng.uniform(0.25, 1.0) * (len(trunk) - 1))]
                _cortical_branch(arteries, rng, margin, f"cortical_{side}", lab, start, 0.8, depth=2)

    for a in arteries:
        a["points"] = a["points"] * p.scale
    if cow["acomm"]:
        pts = catmull_rom(np.array([node["acom_left"], node["acom_right"]])) * p.scale
        arteries.append({"name": "acomm", "label": L.ANTERIOR_LEFT, "points": pts, "radii": np.full(len(pts), 0.6)})
    pts = catmull_rom(jitter([node["ba_low"], (0, 7, -40), (0, 9, -31), node["ba_top"]], 1.0)) * p.scale
    arteries.append({"name": "basilar", "label": L.POSTERIOR, "points": pts, "radii": _taper(len(pts), 1.8, 1.6)})
    return arteries


def _cortical_branch(out, rng, margin, name, label, start, r0, depth) -> None:
    """A branch that wanders over the brain surface, 6-14 mm deep, with side branches.
    Points stay in standard coordinates here; ``build_arteries`` scales them."""
    pos = np.asarray(start, float)
    radial = pos / (np.linalg.norm(pos) + 1e-6)
    d = radial + rng.normal(0, 0.7, 3)
    d /= np.linalg.norm(d)
    pts = [pos.copy()]
    for _ in range(int(rng.integers(6, 13))):
        m = float(margin(pos[None])[0])
        radial = pos / (np.linalg.norm(pos) + 1e-6)
        pull = -radial if m < 6.0 else (radial if m > 14.0 else 0.0 * radial)
        d = d + 0.45 * rng.normal(0, 1, 3) + 0.8 * pull
        d -= 0.3 * radial * float(d @ radial) * (m < 20.0)
        d /= np.linalg.norm(d)
        pos = pos + 4.5 * d
        pts.append(pos.copy())
    pts = catmull_rom(np.array(pts))
    out.append({"name": name, "label": label, "points": pts, "radii": _taper(len(pts), r0, 0.35)})
    if depth > 1:
        for _ in range(int(rng.integers(1, 3))):
            s = pts[int(rng.uniform(0.3, 0.9) * (len(pts) - 1))]
            _cortical_branch(out, rng, margin, name, label, s, 0.55 * r0 + 0.2, depth - 1)


#: Arteries whose first point is a root of the tree (they enter the field from the chest).
ROOT_PREFIXES = ("cca_", "vertebral_")
#: A branch joins the artery whose nearest point lies within this distance (mm) of its first point.
JOIN_MM = 4.0


def path_length_mm(arteries: list[dict]) -> list[np.ndarray]:
    """Per artery, the distance (mm) of each point from the neck along the tree: the roots
    (``ROOT_PREFIXES``) start at 0, every other artery at the path length of the point it
    branches from (the nearest point of a reached artery within ``JOIN_MM``; else, like an
    anastomosis whose parent is far, the farthest point reached so far)."""
    arcs = [np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(a["points"], axis=0), axis=1)))) for a in arteries]
    points = np.concatenate([a["points"] for a in arteries])
    offsets = np.cumsum([0] + [len(a["points"]) for a in arteries])
    firsts = np.stack([a["points"][0] for a in arteries])
    gaps = np.linalg.norm(firsts[:, None, :] - points[None, :, :], axis=2)  # (arteries, all points)
    # per artery n and candidate parent m: the nearest point of m to n's first point, and its path offset
    links: list[list[tuple[int, float]]] = [[] for _ in arteries]
    for n in range(len(arteries)):
        for m in np.flatnonzero(np.minimum.reduceat(gaps[n], offsets[:-1]) <= JOIN_MM):
            if m != n:
                k = int(np.argmin(gaps[n, offsets[m]:offsets[m + 1]]))
                links[n].append((int(m), arcs[m][k] + gaps[n, offsets[m] + k]))
    start = np.array([0.0 if a["name"].startswith(ROOT_PREFIXES) else np.inf for a in arteries])
    for _ in range(len(arteries)):  # shortest paths from the roots (Bellman-Ford over the links)
        before = start.copy()
        for n, parents in enumerate(links):
            for m, along in parents:
                start[n] = min(start[n], start[m] + along)
        if np.array_equal(before, start):
            break
    finite = np.isfinite(start)
    reached = max((s + arc[-1] for s, arc, ok in zip(start, arcs, finite) if ok), default=0.0)
    return [(s if ok else reached) + arc for s, arc, ok in zip(start, arcs, finite)]
