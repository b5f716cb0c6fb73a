"""Training populations: canonicalised CTAs as density + label channels (torch), cached as ``.pt``.

A :class:`TrainingSubject` holds ``(C, K, J, I)`` float densities (channel names in
``CHANNELS``), the voxel-index -> centred-frame matrix (mm) and vessel fiducial
points (centred frame, mm). Populations come from phantoms (generated on the
fly) or from a folder of CTAs with vessel label maps (NIfTI/NRRD/MHA).
"""

from __future__ import annotations

import multiprocessing
import os
import re
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..cta.io import load_cta
from ..cta.masks import cranium_mask_from_cta
from ..render import hu_to_density
from ..volume import Volume
from .canonical import align_to_template, resample_to_template, rigid_error
from ..errors import InputError

#: Density channels of a training subject: total, inside the cranium, inside the vessels.
CHANNELS = ("total", "cranium", "vessels")
#: Vessel fiducial points kept per subject (for the projected-distance loss).
FIDUCIALS = 256
CACHE_FORMAT = "geopose-training-population"
CACHE_VERSION = 1
IMAGE_EXTENSIONS = (".nii.gz", ".nii", ".nrrd", ".mha")
#: Label-map file name = CTA name + one of these suffixes (before the extension).
LABEL_SUFFIXES = ("_vessels", "_labels", "_label", "_seg")


@dataclass
class TrainingSubject:
    """One canonicalised CTA ready for rendering (see module docstring)."""

    name: str
    channels: Tensor
    ijk_to_world: np.ndarray
    fiducials_mm: Tensor

    def to(self, device: torch.device | str) -> "TrainingSubject":
        return TrainingSubject(self.name, self.channels.to(device), self.ijk_to_world, self.fiducials_mm.to(device))


def subject_from_volumes(name: str, cta: Volume, cranium: np.ndarray, vessels: np.ndarray, seed: int = 0) -> TrainingSubject:
    """Channels and fiducials from a CTA (HU) and boolean cranium / vessel masks on its grid."""
    if cranium.shape != cta.array.shape or vessels.shape != cta.array.shape:
        raise InputError(f"{name}: masks {cranium.shape}/{vessels.shape} do not match the CTA grid {cta.array.shape}")
    if not vessels.any():
        raise InputError(f"{name}: the vessel label map is empty; training needs labelled vessels")
    density = torch.as_tensor(hu_to_density(np.ascontiguousarray(cta.array, dtype=np.float32)))
    channels = torch.stack((density, density * torch.as_tensor(cranium), density * torch.as_tensor(vessels)))
    kji = np.argwhere(vessels)
    rng = np.random.default_rng(seed)
    pick = kji[rng.choice(len(kji), size=FIDUCIALS, replace=len(kji) < FIDUCIALS)]
    fiducials = torch.as_tensor(cta.centred_points(pick), dtype=torch.float32)
    return TrainingSubject(name, channels, cta.ijk_to_centred, fiducials)


def phantom_template(template_seed: int, spacing_mm: float) -> tuple[Volume, Volume]:
    """The canonical CTA of phantom ``template_seed`` at ``spacing_mm`` and its cranium mask: the template
    every phantom population is registered to."""
    from ..phantom import labels as L
    from ..phantom import make_subject

    template_cta, template_labels = make_subject(template_seed, spacing_mm=spacing_mm).canonical(spacing_mm)
    return template_cta, template_labels.like(L.cranium_mask(template_labels.array).astype(np.uint8))


def _canonical_phantom(seed: int, spacing_mm: float, template: tuple[Volume, Volume]) -> tuple[TrainingSubject, dict]:
    """One phantom registered to the template on cranium masks; the truth only scores the alignment."""
    from ..phantom import labels as L
    from ..phantom import make_subject

    torch.set_num_threads(1)
    template_cta, template_mask = template
    subject = make_subject(seed, spacing_mm=spacing_mm)
    mask = subject.labels.like(L.cranium_mask(subject.labels.array).astype(np.uint8))
    alignment = align_to_template(mask, template_mask)
    cta = resample_to_template(subject.cta, template_cta, alignment.moving_to_template)
    labels = resample_to_template(subject.labels, template_cta, alignment.moving_to_template, labels=True)
    error = rigid_error(alignment.moving_to_template, subject.native_to_canonical)
    trained = subject_from_volumes(f"phantom-{seed}", cta, L.cranium_mask(labels.array), L.vessel_mask(labels.array), seed)
    return trained, {"seed": seed, **error}


def phantom_population(
    seeds: list[int],
    spacing_mm: float,
    template_seed: int,
    progress: Callable[[str], None] | None = None,
    workers: int = 1,
) -> tuple[list[TrainingSubject], list[dict]]:
    """Phantom subjects canonicalised by registration to the canonical CTA of ``template_seed``.

    Returns the subjects and, per subject, the alignment error of the estimated
    native-to-canonical transform against the phantom's known one (the truth is
    used only for this report). ``workers`` > 1 builds subjects in parallel processes.
    """
    template = phantom_template(template_seed, spacing_mm)
    build = partial(_canonical_phantom, spacing_mm=spacing_mm, template=template)
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            results = list(pool.map(build, seeds))
    else:
        results = [build(seed) for seed in seeds]
    subjects, report = [], []
    for trained, error in results:
        if progress:
            progress(f"phantom {error['seed']}: rotation error {error['rotation_deg']:.2f} deg, translation {error['translation_mm']:.1f} mm")
        subjects.append(trained)
        report.append(error)
    return subjects, report


def _label_file(cta_path: Path) -> Path | None:
    stem = cta_path.name
    for ext in IMAGE_EXTENSIONS:
        if stem.endswith(ext):
            stem = stem[: -len(ext)]
            break
    for suffix in LABEL_SUFFIXES:
        for ext in IMAGE_EXTENSIONS:
            candidate = cta_path.with_name(stem + suffix + ext)
            if candidate.is_file():
                return candidate
    return None


def folder_cases(folder: str | os.PathLike) -> list[tuple[Path, Path]]:
    """(CTA, vessel label map) pairs of a folder: ``NAME.nii.gz`` + ``NAME_vessels.nii.gz`` (or _labels/_label/_seg)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"training folder {folder} does not exist")
    label_pattern = re.compile("(" + "|".join(LABEL_SUFFIXES) + r")\.(nii\.gz|nii|nrrd|mha)$")
    cases = []
    for path in sorted(folder.iterdir()):
        if not path.name.endswith(IMAGE_EXTENSIONS) or label_pattern.search(path.name):
            continue
        labels = _label_file(path)
        if labels is None:
            raise InputError(
                f"{path.name} has no vessel label map; add {path.name.split('.')[0]}_vessels.nii.gz "
                f"(suffix one of {', '.join(LABEL_SUFFIXES)}) or remove the CTA from {folder}"
            )
        cases.append((path, labels))
    if not cases:
        raise InputError(f"{folder} holds no CTA files ({', '.join(IMAGE_EXTENSIONS)}) with vessel label maps")
    return cases


def folder_population(
    folder: str | os.PathLike,
    template: str | os.PathLike | tuple[Volume, Volume] | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[TrainingSubject]:
    """Canonicalised subjects from a folder of CTAs (HU) with vessel label maps (label > 0 = vessel).

    Cranium masks come from the CTA (bone threshold); every CTA is registered on those masks to
    ``template``: a CTA file, a (CTA, cranium mask) pair such as :func:`phantom_template` (the frame
    the phantom populations and the shipped models share), or None for the folder's first case.
    """
    cases = folder_cases(folder)
    if isinstance(template, tuple):
        template_cta, template_mask = template
    else:
        template_cta = load_cta(template if template is not None else cases[0][0])
        template_mask = cranium_mask_from_cta(template_cta)
    subjects = []
    for cta_path, label_path in cases:
        cta = load_cta(cta_path)
        labels = load_cta(label_path, check_hu=False)
        if labels.array.shape != cta.array.shape:
            raise InputError(f"{label_path.name} has grid {labels.array.shape}, its CTA {cta.array.shape}; resample the labels")
        labels = cta.like(np.rint(labels.array).astype(np.int16))
        alignment = align_to_template(cranium_mask_from_cta(cta), template_mask)
        canon = resample_to_template(cta, template_cta, alignment.moving_to_template)
        canon_labels = resample_to_template(labels, template_cta, alignment.moving_to_template, labels=True)
        canon_cranium = resample_to_template(cranium_mask_from_cta(cta), template_cta, alignment.moving_to_template, labels=True)
        if progress:
            progress(f"{cta_path.name}: aligned (mask mismatch {alignment.metric:.2f})")
        subjects.append(subject_from_volumes(cta_path.name, canon, canon_cranium.array > 0, canon_labels.array > 0))
    return subjects


def save_population(path: str | os.PathLike, subjects: list[TrainingSubject], recipe: dict) -> Path:
    """Cache subjects (densities stored float16) with the recipe that made them (JSON-ready dict)."""
    payload = {
        "format": CACHE_FORMAT,
        "version": CACHE_VERSION,
        "recipe": recipe,
        "subjects": [
            {
                "name": s.name,
                "channels": s.channels.half().cpu(),
                "ijk_to_world": torch.as_tensor(s.ijk_to_world),
                "fiducials_mm": s.fiducials_mm.cpu(),
            }
            for s in subjects
        ],
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


def load_population(path: str | os.PathLike, device: torch.device | str = "cpu") -> tuple[list[TrainingSubject], dict]:
    """Subjects and recipe from :func:`save_population` (densities back to float32 on ``device``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"population cache {path} does not exist")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != CACHE_FORMAT or payload.get("version") != CACHE_VERSION:
        raise InputError(f"{path} is not a GeoPose training population (version {CACHE_VERSION}); rebuild it")
    subjects = [
        TrainingSubject(s["name"], s["channels"].float().to(device), s["ijk_to_world"].numpy(), s["fiducials_mm"].to(device))
        for s in payload["subjects"]
    ]
    return subjects, payload["recipe"]
