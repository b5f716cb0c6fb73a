"""Synthetic biplane DSA runs of a phantom subject.

A run is rendered with the project DRR (``geopose.render.DRR``) at a reduced
detector resolution (``render_px`` across) and upsampled to the written matrix.
Frames are *attenuation-like* (contrast, bone residue bright) before they are
stored; the stored DICOM pixels follow ``DSARun.from_attenuation`` (MONOCHROME2,
absorbers dark). Per frame: the bolus (arterial, then a delayed distal arterial
wave and a capillary blush), subtraction residue from small patient motion
(per frame, a slightly moved total-density render minus the mask one), quantum noise
whose level grows with the attenuation behind it (so a MAP shows a grainy
cranium silhouette), detector blur, collimation and a burnt-in text annotation.
Besides the routine catheter positions (``INJECTIONS``, the ones drawn by default),
``DENSE_RUNS`` opacify much more of the head (every territory at high contrast, an
AVM's nidus with early venous drainage, a late phase with the sinuses filled): runs
whose MAP is a vessel blob, for testing what must survive dense opacification.
The written matrix is capped at ``max_matrix_px`` (default 1024, 8-bit), which
keeps a 26-frame run under 30 MB; the physical detector size is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from torch.nn import functional as F

from ..dsa import DSARun
from ..dsa.run import LAT_ROLE, PA_ROLE
from ..dsa.subtraction import MaskSubtraction
from ..geometry.detector import CArmAngles, Detector
from ..geometry.poses import pose_from_carm_angles, project_points
from ..geometry.rigid import RigidTransform
from ..render import DRR
from . import labels as L
from .subject import Subject

__all__ = [
    "Acquisition", "ImagedHead", "SyntheticDSA", "INJECTIONS", "DENSE_RUNS", "DenseRun", "RUNS", "injected_arteries",
    "opacified_labels", "sample_acquisition", "sample_biplane",
    "sample_injection",
    "table_tilt", "dsa_renderer", "simulate_dsa",
]

#: Detector matrices (pixels square) seen clinically (870 to 1920) and their weights.
DETECTOR_MATRICES_PX = (880, 960, 1024, 1240, 1344, 1428, 1440, 1536, 1904, 1920)
DETECTOR_MATRIX_WEIGHTS = (0.05, 0.06, 0.12, 0.1, 0.12, 0.2, 0.12, 0.1, 0.06, 0.07)
SDD_RANGE_MM = (970.0, 1302.0)
SDD_MEDIAN_MM = 1086.0
PRIMARY_RANGE_DEG = (-115.5, 84.0)
FRAMES_RANGE = (3, 26)
FRAMES_MEDIAN = 14
#: Catheter positions and the artery labels they opacify.
INJECTIONS = {
    "ica_left": (L.ICA_LEFT, L.ANTERIOR_LEFT),
    "ica_right": (L.ICA_RIGHT, L.ANTERIOR_RIGHT),
    "cca_left": (L.ICA_LEFT, L.ANTERIOR_LEFT, L.EXTERNAL_LEFT),
    "cca_right": (L.ICA_RIGHT, L.ANTERIOR_RIGHT, L.EXTERNAL_RIGHT),
    "arch": L.ARTERY_LABELS,
}


@dataclass(frozen=True)
class DenseRun:
    """A densely opacified run: the artery labels filled as a routine run fills them, plus
    ``early`` (non-arterial labels filled with the arterial wave) and ``venous`` (labels filled by
    a venous wave peaking ``venous_delay`` bolus widths after the arterial peak, its contrast diluted
    to ``venous_share`` of the arteries'); the vessels' contrast is ``gain`` times a routine run's, the
    capillary blush ``blush_gain`` times, the bolus ``width_factor`` times longer. ``pathology``: what
    the subject must have been drawn with (``make_subject(..., pathology=...)``), if anything."""

    arteries: tuple[int, ...]
    early: tuple[int, ...] = ()
    venous: tuple[int, ...] = ()
    venous_delay: float = 1.0
    venous_share: float = 0.35
    gain: float = 1.0
    blush_gain: float = 1.0
    width_factor: float = 1.0
    pathology: str | None = None


#: Dense runs by name: every territory at high contrast; an AVM (arch injection: the nidus with
#: the arteries, its drain and the sinuses early); a late phase (arteries with the sinuses filled).
DENSE_RUNS = {
    "all_territories": DenseRun(L.ARTERY_LABELS, gain=2.0, blush_gain=5.0, width_factor=1.5),
    "avm": DenseRun(L.ARTERY_LABELS, early=(L.NIDUS,), venous=tuple(L.with_intracranial([L.VENOUS_SINUS])), venous_delay=0.4,
                    gain=1.5, blush_gain=3.0, width_factor=1.3, pathology="avm"),
    "late_venous": DenseRun(L.ARTERY_LABELS, venous=tuple(L.with_intracranial([L.VENOUS_SINUS])), venous_delay=1.2, gain=1.3,
                            blush_gain=3.0, width_factor=1.6),
}
#: Every run ``simulate_dsa`` knows: the routine injections, then the dense runs.
RUNS = tuple(sorted(INJECTIONS)) + tuple(sorted(DENSE_RUNS))
#: Peak log-attenuation of the thickest head path; sets the noise contrast inside vs outside.
HEAD_ATTENUATION = 4.0
STORED_MAX = 255
#: X-ray intensity (stored value, 12 bits) behind no attenuation in a native run.
NATIVE_FULL_INTENSITY = 4000.0
#: Range of the per-run quantum-noise sd (log-attenuation units) behind zero attenuation;
#: it grows like ``exp(attenuation / 2)`` through the head.
QUANTUM_NOISE_SD = (0.010, 0.02)
#: Ray-marching step (mm) of the DSA renders: coarser than the DRR default, for speed.
RENDER_STEP_MM = 1.5
#: Patient motion between the mask and each live frame (zero-mean tremor, drawn per frame):
#: in-plane rotation sd (deg) and shift sd (render pixels) at full amplitude.
MOTION_ROTATION_SD_DEG = 0.3
MOTION_SHIFT_SD_PX = 0.6


#: Head tilt on the angiography table against the head's own axes, sd per Euler angle (deg).
TABLE_TILT_SD_DEG = 4.0


@dataclass(frozen=True)
class Acquisition:
    """One C-arm view as acquired: DICOM angles, the full detector, frames and frame time.

    ``table_rotation`` (3x3) turns the angiography table's axes (those the DICOM
    angles refer to) into the centred native CTA frame: the patient lies on the
    angiography table differently than on the CT table, so the angles alone are
    only the *native* initial guess."""

    view_role: str
    angles: CArmAngles
    detector: Detector
    n_frames: int
    frame_time_ms: float
    table_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def pose(self, isocentre_mm: np.ndarray) -> RigidTransform:
        """True camera-to-world pose (centred native frame) with the isocentre at ``isocentre_mm``."""
        m = pose_from_carm_angles(self.angles)
        m[:3, :] = np.asarray(self.table_rotation, float) @ m[:3, :]
        m[:3, 3] += np.asarray(isocentre_mm, float)
        return RigidTransform(torch.as_tensor(m[None]))


def sample_acquisition(rng: np.random.Generator, view_role: str) -> Acquisition:
    """A clinical-like acquisition: ``view_role`` ``"PA"`` (primary near 0 deg) or ``"LAT"``
    (primary near -90, sometimes +90); SDD 970-1302 mm (median 1086); detector
    880-1920 px square over 270-330 mm; 3-26 frames (median 14) at 2-4 frames/s."""
    role = str(view_role).upper()
    if role not in (PA_ROLE, LAT_ROLE):
        raise ValueError(f"view_role must be {PA_ROLE!r} or {LAT_ROLE!r}, got {view_role!r}")
    if role == PA_ROLE:
        primary = float(np.clip(rng.normal(-3.0, 8.0), -40.0, 40.0))
        secondary = float(np.clip(rng.normal(6.0, 7.0), -25.0, 30.0))
    else:
        side = -1.0 if rng.random() < 0.8 else 1.0
        primary = float(np.clip(side * 90.0 + rng.normal(0.0, 7.0), *PRIMARY_RANGE_DEG))
        secondary = float(np.clip(rng.normal(0.0, 4.0), -15.0, 15.0))
    sdd = float(np.clip(rng.normal(SDD_MEDIAN_MM, 60.0), *SDD_RANGE_MM))
    sod = float(min(rng.uniform(620.0, 780.0), sdd - 280.0))
    n_px = int(rng.choice(DETECTOR_MATRICES_PX, p=np.asarray(DETECTOR_MATRIX_WEIGHTS) / sum(DETECTOR_MATRIX_WEIGHTS)))
    size = rng.uniform(270.0, 330.0)
    det = Detector(n_px, n_px, (size / n_px, size / n_px), sdd)
    frames = int(np.clip(round(rng.lognormal(math.log(FRAMES_MEDIAN), 0.35)), *FRAMES_RANGE))
    frame_time = float(rng.choice([250.0, 1000.0 / 3.0, 500.0]))
    return Acquisition(role, CArmAngles(primary, secondary, sdd, sod), det, frames, frame_time)


def sample_injection(rng: np.random.Generator) -> str:
    """A catheter position (a key of ``INJECTIONS``, never a dense run), uniformly."""
    return str(rng.choice(sorted(INJECTIONS)))


def table_tilt(rng: np.random.Generator) -> np.ndarray:
    """A random 3x3 tilt of the head on the angiography table (``TABLE_TILT_SD_DEG`` per Euler angle)."""
    angles = torch.as_tensor(np.radians(rng.normal(0.0, TABLE_TILT_SD_DEG, (1, 3))))
    return RigidTransform.from_euler_zyx(angles, torch.zeros(1, 3, dtype=torch.float64)).matrix[0, :3, :3].numpy()


def sample_biplane(rng: np.random.Generator, subject: Subject) -> tuple[list[Acquisition], np.ndarray]:
    """A PA and a LAT acquisition sharing one isocentre (centred native mm, the
    head's nominal isocentre plus a random patient offset of about 8 mm) and one
    table rotation: the head's axes in the native frame, tilted by about
    ``TABLE_TILT_SD_DEG`` per axis (the head lies differently than in the CT)."""
    iso = subject.isocentre_native_mm + rng.normal(0.0, 8.0, 3)
    table = subject.head_to_native[:3, :3] @ table_tilt(rng)
    acqs = [replace(sample_acquisition(rng, role), table_rotation=table) for role in (PA_ROLE, LAT_ROLE)]
    return acqs, iso


@dataclass
class SyntheticDSA:
    """A simulated run with its ground truth. ``map`` is the temporal maximum of the
    attenuation-like frames; ``carotids`` maps ``ica_left``/``ica_right`` to projected
    centerline pixels ``(N, 2)`` (row, col) of the written matrix; ``pose`` is the true
    camera-to-world 4x4 in the centred native frame. ``subtraction``: how a native ``run`` is subtracted (None: the
    run is stored subtracted)."""

    run: DSARun
    map: np.ndarray
    cranium_mask: np.ndarray
    carotids: dict[str, np.ndarray]
    pose: np.ndarray
    injection: str
    subtraction: MaskSubtraction | None = None


def opacified_labels(injection: str) -> tuple[list[int], list[int], list[int]]:
    """Label values (``labels.py``) ``injection`` (one of ``RUNS``) fills: ``early`` (the arteries up to
    the circle of Willis, and a dense run's ``early``), ``late`` (the intracranial arteries beyond)
    and ``venous`` (a dense run's venous wave; empty for a routine run)."""
    if injection not in RUNS:
        raise ValueError(f"unknown injection {injection!r}; choose one of {list(RUNS)}")
    dense = DENSE_RUNS.get(injection)
    opac = dense.arteries if dense else INJECTIONS[injection]
    early = list(opac) + [v + L.INTRACRANIAL_OFFSET for v in opac if v in (L.ICA_LEFT, L.ICA_RIGHT)]
    late = [v + L.INTRACRANIAL_OFFSET for v in opac if v not in (L.ICA_LEFT, L.ICA_RIGHT)]
    if dense is None:
        return early, late, []
    return early + list(dense.early), late, list(dense.venous)


def injected_arteries(labels: np.ndarray, injection: str) -> np.ndarray:
    """Bool mask of what ``injection`` fills (``opacified_labels``): the artery labels (``labels.py``,
    intracranial parts included) and, for a dense run, the nidus and the sinuses too."""
    return np.isin(labels, [v for group in opacified_labels(injection) for v in group])


def dsa_renderer(subject: Subject, injection: str, render_px: int = 256) -> DRR:
    """The DRR of ``subject`` with channels total, cranium, early and late arteries opacified by
    ``injection`` (one of ``RUNS``), and for a dense run a fifth, the venous wave's labels."""
    early, late, venous = opacified_labels(injection)
    dense = DENSE_RUNS.get(injection)
    if dense is not None and dense.pathology is not None and not np.any(np.isin(subject.labels.array, list(dense.early))):
        raise ValueError(f"the {injection!r} run needs a subject drawn with pathology={dense.pathology!r}")
    groups = {"cranium": L.label_groups()["cranium"], "early": early, "late": late}
    if dense is not None:
        groups["venous"] = venous
    det = Detector.model().resized(render_px)
    step = max(RENDER_STEP_MM, min(subject.cta.spacing_mm))
    return DRR.from_volume(subject.cta, det, subject.labels, groups, step_mm=step)


def _gamma_variate(t: np.ndarray, t0: float, width: float) -> np.ndarray:
    x = np.clip((t - t0) / width, 0.0, None)
    return (x * np.exp(1.0 - x)) ** 2


def _blur(img: torch.Tensor, sigma_px: float) -> torch.Tensor:
    r = max(1, int(math.ceil(2.5 * sigma_px)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=img.dtype) / sigma_px) ** 2)
    k = k / k.sum()
    x = F.conv2d(F.pad(img, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))


def _moved(img: torch.Tensor, rng: np.random.Generator, amplitude: float) -> torch.Tensor:
    """``img`` (h, w) resampled after a small random in-plane rigid motion about the image
    centre: rotation sd ``amplitude * MOTION_ROTATION_SD_DEG``, shift sd
    ``amplitude * MOTION_SHIFT_SD_PX`` (render pixels), directions drawn independently."""
    a = math.radians(rng.normal(0.0, MOTION_ROTATION_SD_DEG * amplitude))
    h, w = img.shape
    tx, ty = rng.normal(0.0, MOTION_SHIFT_SD_PX * amplitude, 2) * 2.0 / np.array([w, h])
    theta = torch.tensor([[[math.cos(a), -math.sin(a), tx], [math.sin(a), math.cos(a), ty]]], dtype=img.dtype)
    grid = F.affine_grid(theta, (1, 1, h, w), align_corners=False)
    return F.grid_sample(img[None, None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0, 0]


def _burn_text(frames: np.ndarray, rng: np.random.Generator, view: str, primary_deg: float, value: float) -> np.ndarray:
    """Burn a scanner-like annotation into every frame (in place) and return where it lies (bool (H, W)). The side
    marker tells the truth (docs/conventions.md, section 7): in a PA an "R" on the patient's right (the first columns);
    in a lateral the side of the detector ("R" for RAO, negative primary; "L" for LAO) at the last columns."""
    t, h, w = frames.shape
    size = max(10, h // 40)
    font = ImageFont.load_default(size=size)
    layer = Image.new("L", (w, h), 0)
    draw = ImageDraw.Draw(layer)
    lines = [f"PHANTOM {int(rng.integers(1000, 9999))}", f"DSA {view}  {int(rng.integers(70, 90))} kV", f"{rng.integers(2, 5)} F/s"]
    x0, y0 = int(0.04 * w), int(0.04 * h)
    for n, line in enumerate(lines):
        draw.text((x0, y0 + n * int(1.3 * size)), line, fill=255, font=font)
    if view == LAT_ROLE:
        draw.text((int(0.9 * w), int(0.5 * h)), "R" if primary_deg < 0 else "L", fill=255, font=font)
    else:
        draw.text((x0, int(0.5 * h)), "R", fill=255, font=font)
    ink = np.asarray(layer) > 127
    frames[:, ink] = value
    return ink


class ImagedHead(Protocol):
    """What :func:`simulate_dsa` reads of a head besides its renderer."""

    seed: int
    centerlines: list[dict]


def simulate_dsa(
    subject: Subject | ImagedHead,
    acquisition: Acquisition,
    pose: RigidTransform,
    rng: np.random.Generator,
    *,
    injection: str = "cca_left",
    drr: DRR | None = None,
    render_px: int = 256,
    max_matrix_px: int = 1024,
    native: bool = False,
) -> SyntheticDSA:
    """Simulate one DSA run of ``subject`` seen from ``pose`` (camera-to-world, centred
    native frame) with the intrinsics and timing of ``acquisition``. Given ``drr``
    (channels total, cranium, early, late, and venous for a dense run), ``subject`` may be
    any :class:`ImagedHead`, e.g. a real CT whose artery channels are empty (a contrast-free run).
    A dense run (``DENSE_RUNS``) scales the contrast and the bolus width and adds a venous wave. ``native``: the run as
    an angiography system archives it, unsubtracted (X-ray intensities, a mask frame before the T live frames, the
    burnt-in text in each) with the :class:`MaskSubtraction` that subtracts it; the same draws, so the subtracted
    run is the same but for the 8-bit rounding and the text."""
    det_full = acquisition.detector
    det_out = det_full if max(det_full.shape) <= max_matrix_px else det_full.resized(max_matrix_px)
    det_r = det_full.resized(render_px)
    drr = drr or dsa_renderer(subject, injection, render_px)
    T = int(acquisition.n_frames)
    if T < 1:
        raise ValueError(f"a DSA run needs at least one frame, got {T}")

    p0 = pose.matrix.double()
    dense = DENSE_RUNS.get(injection)
    with torch.no_grad():
        channels = drr(RigidTransform(p0.float()), det_r)[0].double()  # total, cranium, early, late[, venous]
    tot0, cran, early, late = channels[:4]
    k_att = HEAD_ATTENUATION / max(float(torch.quantile(tot0.flatten(), 0.995)), 1e-6)
    times = np.arange(T, dtype=float)
    t_peak = rng.uniform(0.15, 0.35) * max(T - 1, 1)
    width = max(1.0, rng.uniform(0.12, 0.25) * T) * (dense.width_factor if dense else 1.0)
    a_early = _gamma_variate(times, t_peak - width, width)
    a_late = _gamma_variate(times, t_peak - 0.6 * width, width)
    capillary = _gamma_variate(times, t_peak + 0.3 * width, 1.8 * width)
    # motion: each live frame sees the head slightly moved against the mask frame (a fresh
    # in-plane shift and rotation of the total-density render, growing over the run); the
    # live minus mask difference is the residue. Directions vary frame to frame, so the MAP
    # shows a residue rim around the head rather than one displaced edge.
    amplitude = np.clip(times / max(T - 1, 1) * rng.uniform(0.3, 1.0) + rng.normal(0, 0.15, T), 0.0, 1.2)
    residue = [_moved(tot0, rng, float(amplitude[t])) - tot0 for t in range(T)]

    vessel_gain = rng.uniform(0.8, 1.2) * k_att * 3.0
    blush = rng.uniform(0.02, 0.06) * k_att
    residue_gain = rng.uniform(0.6, 1.4) * k_att
    venous = torch.zeros_like(early)
    a_venous = np.zeros(T)
    if dense is not None:
        vessel_gain *= dense.gain
        blush *= dense.blush_gain
        if len(channels) > 4:
            venous = dense.venous_share * channels[4]
        # a wider wave peaking venous_delay bolus widths after the arterial peak
        a_venous = _gamma_variate(times, t_peak + (dense.venous_delay - 1.5) * width, 1.5 * width)
    base = torch.stack([
        vessel_gain * (float(a_early[t]) * early + float(a_late[t]) * late + float(a_venous[t]) * venous)
        + blush * float(capillary[t]) * cran
        + residue_gain * residue[t]
        for t in range(T)
    ])[:, None]
    base = _blur(base.float(), rng.uniform(0.5, 1.0))
    H, W = det_out.shape
    signal = F.interpolate(base, size=(H, W), mode="bilinear", align_corners=False)[:, 0]
    atten = F.interpolate(tot0[None, None].float() * k_att, size=(H, W), mode="bilinear", align_corners=False)[0, 0]
    # quantum noise in the log domain: its sd grows like exp(attenuation / 2); mottled
    sigma = rng.uniform(*QUANTUM_NOISE_SD) * torch.exp(0.5 * atten.clamp(max=HEAD_ATTENUATION))
    g = torch.Generator().manual_seed(int(rng.integers(2**31)))
    noise = torch.randn((T, 1, (H + 1) // 2, (W + 1) // 2), generator=g)
    noise = F.interpolate(noise, size=(H, W), mode="bilinear", align_corners=False)[:, 0] * 1.6
    frames = signal + sigma * noise

    # collimation: dark beyond the shutter edges
    margin = rng.uniform(0.0, 0.08, 4)
    r0, r1 = int(margin[0] * H), H - int(margin[1] * H)
    c0, c1 = int(margin[2] * W), W - int(margin[3] * W)
    coll = torch.zeros(H, W, dtype=torch.bool)
    coll[r0:r1, c0:c1] = True

    scale = 0.75 * STORED_MAX / max(float(torch.quantile(signal.amax(0)[::4, ::4].flatten(), 0.999)), 1e-6)
    offset = 0.06 * STORED_MAX
    att = torch.where(coll, frames * scale + offset, torch.zeros_like(frames)).clamp(0, STORED_MAX).round().numpy()
    ink = _burn_text(att, rng, acquisition.view_role, acquisition.angles.primary_deg, STORED_MAX)
    metadata = {"source": "geopose.phantom", "seed": subject.seed, "injection": injection}
    subtraction = None
    if native:  # the mask frame (the head alone) first, then mask + each frame's change; X-ray intensities
        added = torch.cat([torch.zeros((1, H, W)), frames])
        intensity = NATIVE_FULL_INTENSITY * torch.exp(-(atten + added).clamp(min=0.0))
        stored = torch.where(coll, intensity, torch.zeros_like(intensity)).round().numpy()
        stored[:, ink] = NATIVE_FULL_INTENSITY
        run = DSARun(stored, det_out, acquisition.angles, acquisition.frame_time_ms, metadata | {"native": True})
        subtraction = MaskSubtraction(mask_frames=(0,), contrast_frames=tuple(range(1, T + 1)))
    else:
        run = DSARun.from_attenuation(att, det_out, acquisition.angles, acquisition.frame_time_ms, metadata)
    cran_full = F.interpolate(cran[None, None].float(), size=(H, W), mode="bilinear", align_corners=False)[0, 0]
    mask = (cran_full > 0.02 * float(cran.max())).numpy()
    carotids = {}
    for name in ("ica_left", "ica_right"):
        lines = [c["points_mm"] for c in subject.centerlines if c["name"] == name]
        if not lines:
            continue
        pts = np.concatenate(lines)
        px, _ = project_points(p0[0].numpy(), det_out, pts)
        carotids[name] = px
    return SyntheticDSA(run, att.max(0), mask, carotids, p0[0].numpy(), injection, subtraction)
