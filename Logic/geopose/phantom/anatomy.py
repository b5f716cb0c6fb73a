"""The procedural head: sampled parameters and their rasterisation to HU and labels.

*Head coordinates* (mm): RAS axes (+x patient right, +y anterior, +z superior),
origin at the centre of the brain. A subject's head is a "standard head" whose
tissue functions are evaluated at ``x / scale``; its arteries and veins are
polylines built directly in head coordinates. Everything is a smooth function of
position, so the same subject can be rasterised on any grid (native or canonical);
only the scanner's noise and streaks are tied to the grid, like a scanner's.

The CTA is meant to be as hard to segment as a real one: the arterial lumen HU
falls along the tree and varies between subjects (``contrast``), small arteries
are partial-volume blends, the venous sinuses and the dura enhance too
(``veins``), the ICA runs through a dense-bone carotid canal and the cavernous
sinus, some subjects have calcified plaques, and the noise is correlated with
faint streaks from the teeth and petrous bones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import labels as L
from .avm import AVM_STREAM, PATHOLOGIES, add_drainage, build_avm
from .contrast import ENHANCEMENT_STREAM, Enhancement, add_streaks, correlated_noise, lumen_hu, sample_enhancement
from .raster import Grid, SmoothField, rasterise_tube
from .veins import build_veins, ica_segment, petrous
from .vessels import build_arteries

__all__ = ["HeadParams", "sample_head", "rasterise_head"]

HU_AIR = -1000.0


@dataclass
class HeadParams:
    """Everything that varies between phantom subjects (mm, HU)."""

    seed: int
    scale: np.ndarray  # per-axis head scale (x, y, z)
    skull_axes_mm: np.ndarray  # outer skull semi-axes (x, y, z-up, z-down)
    shape_coef: np.ndarray  # low-order shape perturbation of the skull
    skull_thickness_mm: float
    scalp_mm: float
    atrophy: float  # 0..1: wider sulci, CSF and ventricles
    ventricle_scale: float
    hu: dict[str, float]
    noise_sd_hu: float
    hu_gain: float
    hu_offset: float
    cow: dict[str, float]
    tortuosity_mm: float
    arteries: list[dict] = field(default_factory=list)  # name, label, points, radii, hu (lumen HU per point)
    veins: list[dict] = field(default_factory=list)  # name, points, radii
    enhancement: Enhancement | None = None
    avm: dict | None = None  # ``avm.build_avm`` with its ``drain``, for pathology "avm"


#: Thickness (mm) of the carotid canal's wall: dense petrous bone (HU "dense") directly around the petrous ICA's lumen.
CANAL_WALL_MM = 3.0
#: Thickness (mm) of the enhancing dura under the inner table and of the falx.
DURA_MM = 1.2


def sample_head(rng: np.random.Generator, seed: int, pathology: str | None = None) -> HeadParams:
    """Draw one subject's anatomy and appearance parameters. ``rng`` (the subject's main stream)
    draws the head and its arteries; the appearance beyond the tissue HU and the veins come from
    the stream ``[seed, ENHANCEMENT_STREAM]`` (``contrast``); ``pathology`` ``"avm"`` adds an
    arteriovenous malformation from the stream ``[seed, AVM_STREAM]`` (``avm``) and changes nothing else."""
    if pathology is not None and pathology not in PATHOLOGIES:
        raise ValueError(f"unknown pathology {pathology!r}; choose one of {list(PATHOLOGIES)} or None")
    u = rng.uniform
    hu = {
        "grey": u(35, 40), "white": u(26, 31), "csf": u(4, 12), "soft": u(38, 52), "fat": u(-110, -80),
        "cortical": u(1450, 1900), "diploe": u(450, 800), "dense": u(1800, 2300), "teeth": u(2000, 2600),
        # vessel: the bolus, lumen HU of the common carotids; venous: the sinuses, below the arteries' start
        "facial_bone": u(500, 800), "vessel": u(250, 600), "venous": u(160, 360), "globe": u(8, 18),
    }
    hu["venous"] = min(hu["venous"], 0.95 * hu["vessel"])
    cow = {
        "acomm": float(rng.random() > 0.1),
        "pcomm_left": float(rng.choice([0.0, 0.6, 0.9, 1.4], p=[0.2, 0.45, 0.2, 0.15])),
        "pcomm_right": float(rng.choice([0.0, 0.6, 0.9, 1.4], p=[0.2, 0.45, 0.2, 0.15])),
        "a1_left": float(rng.choice([1.2, 0.5], p=[0.9, 0.1])),
        "a1_right": float(rng.choice([1.2, 0.5], p=[0.9, 0.1])),
        "va_left": float(u(1.2, 2.3)),
        "va_right": float(u(1.2, 2.3)),
    }
    p = HeadParams(
        seed=seed,
        scale=rng.normal(1.0, 0.04, 3).clip(0.88, 1.12),
        skull_axes_mm=np.array([72.0, 92.0, 76.0, 88.0]) * rng.normal(1.0, 0.02, 4),
        shape_coef=rng.normal(0.0, 0.025, 5),
        skull_thickness_mm=u(4.5, 8.0),
        scalp_mm=u(4.0, 7.0),
        atrophy=u(0.0, 1.0),
        ventricle_scale=u(0.8, 1.5),
        hu=hu,
        noise_sd_hu=u(5.0, 20.0),
        hu_gain=u(0.97, 1.03),
        hu_offset=u(-5.0, 5.0),
        cow=cow,
        tortuosity_mm=u(1.0, 4.0),
    )
    def margin(pts):
        return inside_cavity_margin(p, pts)

    p.arteries = build_arteries(p, rng, margin)
    look = np.random.default_rng([seed, ENHANCEMENT_STREAM])
    p.enhancement = sample_enhancement(look, p.arteries)
    if pathology == "avm":
        avm_rng = np.random.default_rng([seed, AVM_STREAM])
        p.avm = build_avm(p.arteries, p.scale, avm_rng, margin)
        p.arteries.append(p.avm["feeder"])
    for a, values in zip(p.arteries, lumen_hu(p.arteries, hu["vessel"], p.enhancement, look)):
        a["hu"] = values
    p.veins = build_veins(p.scale, p.arteries, look, margin)
    if p.avm is not None:
        add_drainage(p.avm, p.veins, p.scale, avm_rng, margin)
    return p


# ------------------------------------------------------------------ shape functions
def _ramp(d: np.ndarray, h: float) -> np.ndarray:
    """Partial-volume inside fraction of a signed distance ``d`` (negative inside)."""
    return np.clip(0.5 - d / h, 0.0, 1.0)


def ellipsoid_distance(x, y, z, centre, axes) -> np.ndarray:
    """Signed radial distance (mm) to an ellipsoid surface, negative inside."""
    dx, dy, dz = x - centre[0], y - centre[1], z - centre[2]
    r = np.sqrt(dx * dx + dy * dy + dz * dz)
    q = np.sqrt((dx / axes[0]) ** 2 + (dy / axes[1]) ** 2 + (dz / axes[2]) ** 2)
    return r * (1.0 - 1.0 / np.maximum(q, 1e-6))


SKULL_CENTRE = (0.0, -5.0, 0.0)


def skull_outer_distance(p: HeadParams, x, y, z) -> np.ndarray:
    """Signed distance (mm, standard coordinates) to the outer table of the skull."""
    ax, ay, az_up, az_dn = p.skull_axes_mm
    dx, dy, dz = x - SKULL_CENTRE[0], y - SKULL_CENTRE[1], z - SKULL_CENTRE[2]
    az = np.where(dz > 0, az_up, az_dn).astype(np.float32)
    r = np.sqrt(dx * dx + dy * dy + dz * dz) + 1e-6
    q = np.sqrt((dx / ax) ** 2 + (dy / ay) ** 2 + (dz / az) ** 2) + 1e-6
    ux, uy, uz = dx / r, dy / r, dz / r
    c = [float(v) for v in p.shape_coef]
    bump = 1.0 + c[0] * uy + c[1] * uz + c[2] * uy * uz + c[3] * (ux * ux - uy * uy) + c[4] * ux * uy
    # a slightly flatter forehead and a fuller occiput
    bump = bump - 0.03 * np.clip(uy - 0.6, 0, None) + 0.03 * np.clip(-uy - 0.5, 0, None)
    return r - (r / q) * bump


def skull_thickness(p: HeadParams, x, y, z) -> np.ndarray:
    """Vault thickness (mm) by direction: thin temporal squama, thick occiput and frontal bone."""
    dx, dy, dz = x - SKULL_CENTRE[0], y - SKULL_CENTRE[1], z - SKULL_CENTRE[2]
    r = np.sqrt(dx * dx + dy * dy + dz * dz) + 1e-6
    ux, uy, uz = dx / r, dy / r, dz / r
    temporal = np.clip((np.abs(ux) - 0.55) / 0.4, 0, 1) * np.clip(1.0 - np.abs(uz + 0.1) / 0.55, 0, 1)
    t = 1.0 + 0.35 * np.clip(-uy, 0, None) ** 2 + 0.15 * np.clip(uy, 0, None) - 0.5 * temporal
    return p.skull_thickness_mm * t


def skull_base_height(x, y) -> np.ndarray:
    """Height (mm) of the cranial floor: anterior, middle and posterior fossae, sella."""
    w_ant = 1.0 / (1.0 + np.exp(-(y - 22.0) / 4.0))
    w_post = 1.0 / (1.0 + np.exp(-(-8.0 - y) / 5.0))
    w_mid = np.clip(1.0 - w_ant - w_post, 0.0, 1.0)
    ant = -22.0 - 6.0 * np.exp(-((x / 10.0) ** 2))
    mid = -50.0 + 20.0 * np.exp(-((x / 15.0) ** 2))
    post = -60.0 - 5.0 * np.exp(-((x / 30.0) ** 2))
    return w_ant * ant + w_mid * mid + w_post * post


SKULL_BASE_MM = 8.0


def inside_cavity_margin(p: HeadParams, pts: np.ndarray) -> np.ndarray:
    """Depth (mm) of standard-coordinate points ``(N, 3)`` inside the cranial cavity (negative outside)."""
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    d_in = skull_outer_distance(p, x, y, z) + skull_thickness(p, x, y, z)
    return np.minimum(-d_in, z - skull_base_height(x, y))


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


# ------------------------------------------------------------------ rasterisation
def _tube(grid: Grid, scale: np.ndarray, pts, radii) -> np.ndarray:
    cov = np.zeros(grid.shape_kji, np.float32)
    rasterise_tube(grid, np.asarray(pts, float) * scale, np.broadcast_to(np.asarray(radii, float), (len(pts),)), cov)
    return cov


def _local_ellipsoid(grid: Grid, scale: np.ndarray, X, Y, Z, centre, axes, margin: float = 3.0):
    """Slices of the grid around an ellipsoid (standard coordinates) and its signed
    distance there; None when it misses the grid."""
    c, ax = np.asarray(centre, float), np.asarray(axes, float) + margin
    sl = grid.box((c - ax) * scale, (c + ax) * scale)
    if sl is None:
        return None, None
    return sl, ellipsoid_distance(X[sl], Y[sl], Z[sl], centre, axes)


def _mix(hu: np.ndarray, frac: np.ndarray, value) -> None:
    """``hu <- hu + frac * (value - hu)`` in place."""
    hu += frac * (value - hu)


def rasterise_head(p: HeadParams, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """HU ``(K, J, I)`` float32 and labels uint8 of subject ``p`` on ``grid`` (head coordinates)."""
    X0, Y0, Z0 = grid.coords
    s = p.scale.astype(np.float32)
    X, Y, Z = X0 / s[0], Y0 / s[1], Z0 / s[2]
    h = grid.voxel_mm
    hu_p = p.hu
    frng = np.random.default_rng(p.seed + 7919)
    tex = SmoothField(frng, 24.0).on_grid(grid, 4.0)
    g = SmoothField(frng, 7.0).on_grid(grid, 2.0)
    ftex = SmoothField(frng, 3.0).on_grid(grid, 1.0)

    # --- body outline: scalp over the skull, face, nose, neck
    d_out = skull_outer_distance(p, X, Y, Z)
    d_face = ellipsoid_distance(X, Y, Z, (0, 36, -72), (58, 60, 50))
    d_nose = ellipsoid_distance(X, Y, Z, (0, 86, -50), (11, 15, 22))
    rn = np.sqrt((X / 52.0) ** 2 + ((Y + 8.0) / 50.0) ** 2)
    d_neck = np.maximum((rn - 1.0) * 50.0, Z + 60.0)
    d_body = _smin(_smin(d_out - p.scalp_mm, d_face, 12.0), _smin(d_nose, d_neck, 8.0), 10.0)
    del d_face, d_nose, rn, d_neck
    hu = np.full(grid.shape_kji, HU_AIR, np.float32)
    _mix(hu, _ramp(d_body, h), hu_p["soft"] + 4.0 * tex)
    _mix(hu, _ramp(d_body, h) * _ramp(-d_body - 4.0, h) * (d_out > 0), hu_p["fat"])

    # --- face: orbits, palate, zygoma, teeth, mandible, cervical spine
    for sx in (-1.0, 1.0):
        sl, d_orb = _local_ellipsoid(grid, p.scale, X, Y, Z, (33 * sx, 60, -42), (16, 24, 17))
        if sl is not None:
            _mix(hu[sl], _ramp(np.abs(d_orb) - 1.0, h) * (Y[sl] < 70), hu_p["facial_bone"])
            _mix(hu[sl], _ramp(d_orb, h), hu_p["fat"])
        sl, d_eye = _local_ellipsoid(grid, p.scale, X, Y, Z, (33 * sx, 72, -42), (12, 12, 12))
        if sl is not None:
            _mix(hu[sl], _ramp(d_eye, h), hu_p["globe"])
    sl = grid.box(np.array([-30.0, 22.0, -88.0]) * p.scale, np.array([30.0, 88.0, -76.0]) * p.scale)
    if sl is not None:
        box = np.maximum.reduce([np.abs(X[sl]) - 28.0, np.abs(Y[sl] - 55.0) - 30.0, np.abs(Z[sl] + 82.0) - 3.0])
        _mix(hu[sl], _ramp(box, h), hu_p["facial_bone"] + 200)
    bones = []
    for sx in (-1.0, 1.0):
        bones.append(([(48 * sx, 62, -52), (58 * sx, 40, -54), (62 * sx, 12, -52), (58 * sx, -6, -48)], 4.0, 1100))
        # mandible: condyle, ramus, angle, body to the chin (two stacked tubes for its height)
        bones.append(([(50 * sx, 0, -50), (49 * sx, 4, -75), (46 * sx, 4, -104), (40 * sx, 34, -112), (22 * sx, 66, -116), (0, 80, -118)], 6.0, 1250))
        bones.append(([(44 * sx, 30, -100), (24 * sx, 60, -102), (0, 74, -104)], 6.5, 1000))
        bones.append(([(27 * sx, 30, -90), (24 * sx, 60, -91), (0, 76, -92)], 4.5, hu_p["teeth"]))
        bones.append(([(27 * sx, 28, -97), (22 * sx, 58, -98), (0, 72, -99)], 4.0, hu_p["teeth"]))
        # petrous ridge and mastoid
        bones.append(([(56 * sx, -30, -50), (38 * sx, -15, -46), (18 * sx, 2, -43)], 7.0, hu_p["dense"]))
        bones.append(([(55 * sx, -25, -52), (54 * sx, -22, -70)], 7.0, 900))
    bones.append(([(0, 6, -36), (0, -2, -50), (0, -8, -62)], 7.0, 1100))  # clivus
    # cervical spine: C1 ring, dens, C2-C7 bodies and arches
    z_c1 = -76.0
    ring = [(18 * np.sin(a), -14 + 18 * np.cos(a), z_c1) for a in np.linspace(0, 2 * np.pi, 17)]
    bones.append((ring, 3.5, 1100))
    bones.append(([(0, 0, -98), (0, 0, -70)], 5.5, 900))
    for n in range(6):
        zc = -100.0 - 19.0 * n
        yc = -2.0 + 0.02 * (zc + 100.0) ** 2 / 10.0
        bones.append(([(0, yc, zc - 6.5), (0, yc, zc + 6.5)], 8.5, 1000))
        arch = [(14 * np.sin(a), yc - 22 + 11 * np.cos(a), zc) for a in np.linspace(0.5 * np.pi, 1.5 * np.pi, 9)]
        bones.append((arch, 3.5, 1100))
        bones.append(([(0, yc - 33, zc), (0, yc - 50, zc - 8)], 3.5, 1000))
        bones.append(([(-24, yc - 12, zc), (24, yc - 12, zc)], 3.0, 900))
    cov = np.zeros(grid.shape_kji, np.float32)
    val = np.zeros(grid.shape_kji, np.float32)
    inner = np.zeros(grid.shape_kji, np.float32)
    for pts, r, v in bones:
        pts = np.asarray(pts, float) * p.scale
        rasterise_tube(grid, pts, np.full(len(pts), r), cov, val, v, min_cover=0.0)
        rasterise_tube(grid, pts, np.full(len(pts), max(r - 2.0, 1.0)), inner)
    _mix(hu, cov * _ramp(d_body, h), val * (1.0 + 0.1 * ftex))
    _mix(hu, inner, 0.45 * val)
    del cov, val, inner

    # --- air: nasal cavity, paranasal sinuses, pharynx
    sl = grid.box(np.array([-48.0, 10.0, -84.0]) * p.scale, np.array([48.0, 90.0, -22.0]) * p.scale)
    if sl is not None:
        x, y, z = X[sl], Y[sl], Z[sl]
        d_air = np.minimum.reduce([
            ellipsoid_distance(x * (1.0 + 0.012 * (z + 55.0)), y, z, (0, 58, -55), (11, 28, 25)),
            ellipsoid_distance(x, y, z, (30, 56, -62), (13, 17, 16)),
            ellipsoid_distance(x, y, z, (-30, 56, -62), (13, 17, 16)),
            ellipsoid_distance(x, y, z, (0, 18, -46), (11, 9, 8)),
            ellipsoid_distance(x, y, z, (0, 55, -32), (9, 16, 6)),
        ])
        _mix(hu[sl], _ramp(np.abs(d_air - 1.2) - 0.8, h), hu_p["facial_bone"])
        _mix(hu[sl], _ramp(d_air, h) * (np.abs(x) > 1.0), HU_AIR)
    sl, d_front = _local_ellipsoid(grid, p.scale, X, Y, Z, (0, 80, -4), (13, 3.5, 9))
    if sl is not None:
        _mix(hu[sl], _ramp(d_front, h), HU_AIR)
    airway = _tube(grid, p.scale, [(0, 42, -72), (0, 24, -86), (0, 16, -110), (0, 18, -140), (0, 20, -200)], 8.0)
    _mix(hu, airway, HU_AIR)
    del airway

    # --- cranium: vault and base bone with tables and diploe, then the cavity
    t = skull_thickness(p, X, Y, Z)
    d_in = d_out + t
    z_b = skull_base_height(X, Y)
    fm = (np.sqrt(X ** 2 + (Y + 22.0) ** 2) < 15.0) & (Z < z_b + 2.0)
    bone_frac = _ramp(d_out, h) * _ramp((z_b - SKULL_BASE_MM) - Z, h) * ~fm
    cav_frac = _ramp(d_in, h) * _ramp(z_b - Z, h)
    edge = np.minimum.reduce([-d_out, np.maximum(d_in, z_b - Z), Z - (z_b - SKULL_BASE_MM)])
    table = np.clip(0.22 * t, 1.2, 2.2)
    cort = _ramp(edge - table, h)
    bone_hu = hu_p["diploe"] * (1.0 + 0.25 * ftex) + (hu_p["cortical"] - hu_p["diploe"]) * cort
    _mix(hu, bone_frac * (1.0 - cav_frac), bone_hu)
    cranium = (d_out < 0) & (Z > z_b - SKULL_BASE_MM)
    del bone_hu, cort, edge, bone_frac

    # brain: CSF rim, folded cortex, white matter, deep grey, fissure, ventricles, cisterns
    depth = np.minimum(-d_in, Z - z_b) - (1.5 + 2.0 * p.atrophy)
    brain = np.where(depth < 2.5 + 4.0 * np.clip(g, 0, None), hu_p["grey"], hu_p["white"]).astype(np.float32)
    brain += 2.0 * tex
    for sx in (-1.0, 1.0):
        for centre, axes in (((11 * sx, -8, 2), (9, 14, 9)), ((21 * sx, 8, 4), (7, 14, 10))):
            sl, d_deep = _local_ellipsoid(grid, p.scale, X, Y, Z, centre, axes)
            if sl is not None:
                _mix(brain[sl], _ramp(d_deep, h), hu_p["grey"] - 2.0)
    csf = _ramp(depth, h)
    csf = np.maximum(csf, (depth < 14.0) * _ramp(1.25 - 0.5 * p.atrophy - g, 0.4 * h))
    csf = np.maximum(csf, _ramp(np.abs(X) - 1.0 - p.atrophy, h) * (Z > z_b + 10.0))
    del g, depth
    vs = p.ventricle_scale
    vent = np.zeros(grid.shape_kji, np.float32)
    for sx in (-1.0, 1.0):
        path = [(9 * sx, 28, 6), (10 * sx, 12, 14), (11 * sx, -8, 16), (17 * sx, -26, 10), (18 * sx, -42, 4)]
        rasterise_tube(grid, np.asarray(path) * p.scale, np.array([4.5, 4.5, 4.0, 5.0, 2.5]) * vs, vent)
        temporal = [(17 * sx, -26, 10), (26 * sx, -20, -6), (28 * sx, 0, -22), (26 * sx, 8, -26)]
        rasterise_tube(grid, np.asarray(temporal) * p.scale, np.array([4.0, 3.0, 2.0, 1.5]) * vs, vent)
    rasterise_tube(grid, np.array([(0, 10, -2), (0, -6, -6)]) * p.scale, np.array([2.0, 2.0]) * vs, vent)
    rasterise_tube(grid, np.array([(0, -28, -40), (0, -30, -46)]) * p.scale, np.array([4.0, 3.0]), vent)
    rasterise_tube(grid, np.array([(-12, 6, -28), (12, 6, -28)]) * p.scale, np.array([7.0, 7.0]), vent)
    csf = np.maximum(csf, vent)
    del vent
    _mix(brain, csf, hu_p["csf"])
    stem = _tube(grid, p.scale, [(0, -4, -14), (0, -12, -40), (0, -22, -64), (0, -22, -90)], 10.0)
    _mix(brain, stem, hu_p["white"] + 4.0)
    del stem, csf
    _mix(hu, cav_frac, brain)
    del brain
    # enhancing dura: a thin layer under the inner table (and over the cranial floor), and the falx
    wall = np.minimum(-d_in, Z - z_b)
    dura = cav_frac * np.maximum(_ramp(np.abs(wall - 0.5 * DURA_MM) - 0.5 * DURA_MM, h),
                                 _ramp(np.abs(X) - 0.5 * DURA_MM, h) * (Z > 15.0) * (wall > 0))
    _mix(hu, dura, p.enhancement.dura_hu)
    del cav_frac, wall, d_in, z_b
    # dense petrous bone on top of the brain boundary, and the carotid canal around the petrous ICA
    for sx in (-1.0, 1.0):
        _mix(hu, _tube(grid, p.scale, [(56 * sx, -30, -50), (38 * sx, -15, -46), (18 * sx, 2, -43)], 6.0), hu_p["dense"])
    canal = np.zeros(grid.shape_kji, np.float32)
    for side in ("left", "right"):
        pts, radii = ica_segment(p.arteries, side, p.scale, petrous)
        if len(pts) >= 2:
            rasterise_tube(grid, pts, radii + CANAL_WALL_MM, canal)
    _mix(hu, canal, hu_p["dense"])
    del canal

    # --- labels, veins, arteries (each lumen with its own HU along it), calcified plaques
    lab = cranium.astype(np.uint8) * np.uint8(L.CRANIUM)
    lab[cranium & (dura > 0.5)] = L.DURA
    del dura
    cov = np.zeros(grid.shape_kji, np.float32)
    vlab = np.zeros(grid.shape_kji, np.uint8)
    for vein in p.veins:
        rasterise_tube(grid, vein["points"], vein["radii"], cov, vlab, L.VENOUS_SINUS)
    _mix(hu, cov, hu_p["venous"])
    cov[:] = 0.0
    value = np.zeros(grid.shape_kji, np.float32)
    for art in p.arteries:
        rasterise_tube(grid, art["points"], art["radii"], cov, vlab, art["label"], values=value, point_values=art["hu"])
    _mix(hu, cov, value)
    if p.avm is not None:  # nidus at its feeder's HU, the drain between it and the sinuses
        cov[:] = 0.0
        nidus = np.zeros(grid.shape_kji, np.uint8)
        feeder_hu = float(p.avm["feeder"]["hu"][-1])
        for tube in p.avm["nidus"]:
            rasterise_tube(grid, tube["points"], tube["radii"], cov, nidus, L.NIDUS)
        _mix(hu, cov, feeder_hu)
        cov[:] = 0.0
        rasterise_tube(grid, p.avm["drain"]["points"], p.avm["drain"]["radii"], cov, nidus, L.NIDUS)
        _mix(hu, cov, 0.5 * (feeder_hu + hu_p["venous"]))
        lab[(nidus > 0) & cranium & (vlab == 0)] = L.NIDUS
        del nidus
    cov[:] = 0.0
    value[:] = 0.0
    for q in p.enhancement.plaques:
        c = np.asarray(q["centre_mm"], float)
        rasterise_tube(grid, np.stack([c, c]), np.full(2, q["radius_mm"]), cov, value, q["hu"], min_cover=0.0)
    _mix(hu, cov, value)
    vessel = vlab > 0
    lab[vessel] = vlab[vessel] + np.where(cranium[vessel], L.INTRACRANIAL_OFFSET, 0).astype(np.uint8)
    del cov, vlab, value

    # --- calibration, correlated noise and streaks (tied to the grid, like a scanner's)
    white = np.random.default_rng(p.seed + 104729).standard_normal(grid.shape_kji, dtype=np.float32)
    hu = hu * p.hu_gain + p.hu_offset + p.noise_sd_hu * correlated_noise(white, p.enhancement.noise_neighbour_weight)
    del white
    add_streaks(hu, grid, p.scale, p.enhancement.streaks)
    return np.clip(np.rint(hu), -1024, 3071).astype(np.float32), lab
