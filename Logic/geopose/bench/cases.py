"""Benchmark cases with known poses: held-out phantom subjects (written and read
back through the real file formats) and a real head CT with simulated runs, as it is
(no contrast) or made into a CTA with a phantom's arteries (``phantom.real_head``).

Seeds of benchmark phantoms must be disjoint from the shipped models' training
seeds (``Resources/Models/manifest.json``); :func:`training_seeds` reads them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..cta import cranium_mask_from_cta, load_cta
from ..dsa import DSARun, read_dsa
from ..phantom import labels as L
from ..phantom.cli import write_phantom
from ..phantom.dsa import dsa_renderer, sample_acquisition, sample_injection, simulate_dsa, table_tilt
from ..phantom.real_head import load_headsq, with_arteries
from ..dsa.run import LAT_ROLE, PA_ROLE
from ..geometry import Detector
from ..register.evaluate import load_truth
from ..render import DRR
from ..volume import Volume
from ..errors import InputError

__all__ = [
    "BenchCase", "phantom_case", "real_head_case", "headsq_case", "ge_head_case", "training_seeds", "seed_range",
    "flipped_left_right",
]

#: Matrix cap (px) of the simulated runs: enough for the 256 px model input.
BENCH_MATRIX_PX = 512
#: Case-name suffix of a real head CT given a phantom's arteries.
ARTERIES_SUFFIX = "+arteries"


@dataclass
class BenchCase:
    """One case: the CTA (HU) with its masks on the CTA grid, a PA + lateral run,
    the true poses ``{"pa", "lat"} -> (4, 4)`` (camera-to-centred-native, mm) and the
    carotid centreline points ``(N, 3)`` (centred native mm; ``None`` without arteries)."""

    name: str
    cta: Volume
    cranium: Volume
    vessels: Volume | None
    runs: dict[str, DSARun]
    true_poses: dict[str, np.ndarray]
    carotid_points_mm: np.ndarray | None
    notes: list[str] = field(default_factory=list)


def training_seeds(manifest: str | Path) -> set[int]:
    """Phantom seeds the models in ``manifest`` were trained on (template included)."""
    models = json.loads(Path(manifest).read_text()).get("models", {})
    seeds: set[int] = set()
    for entry in models.values():
        data = entry.get("training", {}).get("data", {})
        seeds.update(int(s) for s in data.get("seeds", []))
        if "template_seed" in data:
            seeds.add(int(data["template_seed"]))
    return seeds


def seed_range(text: str) -> list[int]:
    """Seeds written ``"5000-5039"`` (inclusive) or ``"5000"``."""
    lo, _, hi = text.partition("-")
    try:
        return list(range(int(lo), int(hi or lo) + 1))
    except ValueError:
        raise InputError(f"seed range {text!r}: write FIRST-LAST or one seed, e.g. 5000-5039") from None


def phantom_case(seed: int, folder: Path, spacing_mm: float = 1.0, injection: str | None = None,
                 native_runs: bool = False) -> BenchCase:
    """Phantom ``seed`` written by ``geopose phantom`` into ``folder`` and read back, its runs with
    ``injection`` (default: the subject's own draw; the case is then named after it too); the
    phantom's own cranium and artery labels are the true masks (scoring and upper bounds). ``native_runs``: the runs
    archived native and read subtracted by their Mask Subtraction Sequence, as ``read_dsa`` reads such files."""
    write_phantom(seed, folder, spacing_mm=spacing_mm, injection=injection, max_matrix_px=BENCH_MATRIX_PX,
                  native_runs=native_runs)
    cta = load_cta(folder / "cta.nii.gz")
    labels = load_cta(folder / "labels.nii.gz", check_hu=False)
    truth = load_truth(folder / "cta.nii.gz")
    runs = {key: read_dsa(folder / f"dsa_{key}.dcm") for key in ("pa", "lat")}
    return BenchCase(
        f"phantom-{seed}" + (f"-{injection}" if injection else ""), cta, labels.like(L.cranium_mask(labels.array).astype(np.uint8)),
        labels.like(L.vessel_mask(labels.array).astype(np.uint8)), runs, truth.poses, truth.carotid_points_mm,
    )


def flipped_left_right(cta: Volume) -> Volume:
    """``cta`` with its array flipped along the axis nearest the patient's left-right, the header kept: what a CTA
    whose header swaps the patient's sides gives (the input the mirror test, ``register/mirror.py``, must fail)."""
    axis = 2 - int(np.argmax(np.abs(cta.ijk_to_ras[0, :3]) / np.asarray(cta.spacing_mm)))
    return cta.like(np.ascontiguousarray(np.flip(cta.array, axis)))


@dataclass
class _RealHead:
    """What ``simulate_dsa`` reads of a real head, and ``dsa_renderer`` (CTA and labels) with arteries."""

    seed: int
    centerlines: list[dict] = field(default_factory=list)
    cta: Volume | None = None
    labels: Volume | None = None


def real_head_case(name: str, cta: Volume, seed: int, notes: list[str], *, arteries: bool = False) -> BenchCase:
    """A real head CT (HU, no contrast) with a PA + lateral run simulated from it at sampled
    clinical geometries, the head tilted on the angiography table as in the phantom world
    (``table_tilt``): the runs hold motion residue and noise only, so the measurable results
    are pose errors, NCC and the cranium silhouette. Its vessel segmentation is empty: neither
    the CT nor the runs show opacified vessels, so the registration has no vessel term (the
    approximate mask of a non-contrast CT would hold dura and calcifications, compared with noise).

    ``arteries``: the CT is first made a CTA with the arteries of phantom ``seed``
    (:func:`~geopose.phantom.real_head.with_arteries`); its vessel segmentation is their mask, the
    runs show those of an injection drawn from the seed as ``write_phantom`` draws it, and the ICA
    centrelines give the carotid points (mPCD). The geometry is the plain case's of the same seed."""
    cranium = cranium_mask_from_cta(cta)
    rng = np.random.default_rng([seed, 7])
    k, j, i = np.nonzero(cranium.array)
    centroid = (cta.ijk_to_centred @ np.array([i.mean(), j.mean(), k.mean(), 1.0]))[:3]
    iso = centroid + rng.normal(0.0, 8.0, 3)
    if arteries:
        cta, labels, lines = with_arteries(cta, seed, cranium=cranium)
        injection = sample_injection(np.random.default_rng([seed, 1]))
        head = _RealHead(seed, lines, cta, labels)
        drr = dsa_renderer(head, injection)
        vessels = labels.like(L.vessel_mask(labels.array).astype(np.uint8))
        carotid = [c["points_mm"] for c in lines if c["label"] in (L.ICA_LEFT, L.ICA_RIGHT)]
        fit = cta.metadata["arteries"]
        notes = notes + [
            f"{name}{ARTERIES_SUFFIX}: arteries of phantom seed {seed} fitted into the CT's cranial cavity (scales "
            f"{', '.join(f'{v:.2f}' for v in fit['scales'])}, cavity rms {fit['cavity_rms_mm']:.1f} mm; neck shifted "
            f"{np.linalg.norm(fit['neck_shift_mm']):.0f} mm onto the CT's spine), painted at {fit['vessel_hu']:.0f} HU "
            f"and clipped to the field of view; runs with the {injection} injection; mPCD on their ICA centrelines"]
        name = name + ARTERIES_SUFFIX
    else:
        head, injection = _RealHead(seed), "cca_left"  # simulate_dsa's default; these runs show no arteries
        drr = DRR.from_volume(cta, Detector.model().resized(256), cranium, {"cranium": [1], "early": [], "late": []})
        vessels = cta.like(np.zeros(cta.array.shape, np.uint8))
        carotid = []
        notes = notes + ["runs simulated from the CT itself (motion residue + noise, no arteries): no mPCD or clDice, "
                         "no vessel term"]
    runs, poses = {}, {}
    table = table_tilt(rng)
    for key, role in (("pa", PA_ROLE), ("lat", LAT_ROLE)):
        acq = replace(sample_acquisition(rng, role), table_rotation=table)
        sim = simulate_dsa(head, acq, acq.pose(iso), rng, injection=injection, drr=drr, max_matrix_px=BENCH_MATRIX_PX)
        runs[key], poses[key] = sim.run, sim.pose
    carotid_points = np.concatenate(carotid) if carotid else None
    return BenchCase(f"{name}-{seed}", cta, cranium, vessels, runs, poses, carotid_points, notes)


def headsq_case(path: str | Path, seed: int = 0, *, arteries: bool = False) -> BenchCase:
    """The real head CT ``headsq`` (``quarter_sidecar.mhd``) with simulated runs (:func:`real_head_case`)."""
    return real_head_case("headsq", load_headsq(path), seed, [
        "headsq: real CT without contrast, 3.2 x 3.2 x 1.5 mm, header turned 180 deg about A (it is upside down)"],
        arteries=arteries)


def ge_head_case(folder: str | Path, seed: int = 0, *, arteries: bool = False) -> BenchCase:
    """The real GE head CT (a DICOM series with gantry tilt, resampled by ``load_cta``) with
    simulated runs (:func:`real_head_case`)."""
    cta = load_cta(folder)
    geo = cta.metadata.get("slice_geometry", {})
    how = (f"{geo['reason']} ({geo.get('gantry_tilt_deg', 0):.1f} deg), resampled onto {geo['slice_spacing_mm']:.2f} mm slices"
           if geo.get("resampled") else "regular slices")
    spacing = " x ".join(f"{s:.2f}" for s in cta.spacing_mm)
    return real_head_case("ge-head", cta, seed, [f"GE head CT (DICOM, {spacing} mm): {how}"], arteries=arteries)
