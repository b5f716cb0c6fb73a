"""Densely opacified phantom cases for the cranium-mask benchmark (experiments/cranium_masks/cranium_masks.md), made
with the existing simulator until the phantom world has its own dense injections: every artery
label opacified (the ``arch`` injection) with ``DENSE_VESSEL_GAIN`` times the world's contrast, and
an AVM-like nidus (a sphere of opacified intracranial artery label, also in the CTA). The vessels
then take the top of each run's 8-bit range and the head's noise-drawn level drops to a few grey
levels, as in an AVM, a late arterial phase or a bilateral injection.

    python experiments/cranium_masks/dense_runs.py --seeds 5000-5004 --out /tmp/dense   # one folder per seed, as `geopose phantom`
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.dsa import write_dsa_dicom  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402
from geopose.phantom.cli import _write_volume  # noqa: E402
from geopose.phantom.dsa import dsa_renderer, sample_biplane, sample_injection, simulate_dsa  # noqa: E402
from geopose.phantom.subject import Subject, make_subject  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

#: Contrast of the dense runs' vessels against the phantom world's (``simulate_dsa``'s vessel gain).
DENSE_VESSEL_GAIN = 5.0
#: Radius range (mm) of the nidus and its CTA value (HU, an opacified lumen).
NIDUS_RADIUS_MM = (10.0, 18.0)
NIDUS_HU = 400.0
#: The nidus centre lies at least this far (mm) inside the cranium label's surface, beyond its radius.
NIDUS_DEPTH_MM = 15.0


class _Opacified(torch.nn.Module):
    """A DSA renderer (channels total, cranium, early, late) whose artery channels are ``gain`` times stronger."""

    def __init__(self, drr: torch.nn.Module, gain: float) -> None:
        super().__init__()
        self.drr, self.gain = drr, float(gain)

    def forward(self, pose, detector):
        out = self.drr(pose, detector).clone()
        out[:, 2:] *= self.gain
        return out


def add_nidus(subject: Subject, rng: np.random.Generator) -> dict:
    """Paint an AVM-like nidus into ``subject`` (in place): a sphere of ``NIDUS_RADIUS_MM`` radius deep
    in the cranium, labelled as intracranial left anterior circulation, ``NIDUS_HU`` in the CTA.
    Returns its centre (centred native mm) and radius (mm)."""
    labels, cta = subject.labels, subject.cta
    cranium = L.cranium_mask(labels.array)
    radius = float(rng.uniform(*NIDUS_RADIUS_MM))
    spacing = np.asarray(cta.spacing_mm)[::-1]  # [k, j, i]
    depth = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(
        sitk.GetImageFromArray((~cranium).astype(np.uint8)), insideIsPositive=False, useImageSpacing=False,
        squaredDistance=False))  # voxels from the cranium's outside: positive inside it
    deep = np.argwhere(depth * spacing.min() > radius + NIDUS_DEPTH_MM)
    k, j, i = deep[rng.integers(len(deep))]
    kk, jj, ii = np.indices(labels.array.shape, sparse=True)
    inside = ((kk - k) * spacing[0]) ** 2 + ((jj - j) * spacing[1]) ** 2 + ((ii - i) * spacing[2]) ** 2 <= radius**2
    labels.array[inside] = L.ANTERIOR_LEFT + L.INTRACRANIAL_OFFSET
    cta.array[inside] = np.maximum(cta.array[inside], NIDUS_HU)
    centre = (cta.ijk_to_centred @ np.array([i, j, k, 1.0]))[:3]
    return {"centre_mm": centre.tolist(), "radius_mm": radius}


def write_dense_phantom(seed: int, out: Path, *, spacing_mm: float = 1.0, max_matrix_px: int = 512) -> dict:
    """Phantom ``seed`` with a nidus and densely opacified runs, written as ``geopose phantom`` writes
    a subject (``cta.nii.gz``, ``labels.nii.gz``, ``centerlines.json``, ``truth.json``, ``dsa_pa.dcm``,
    ``dsa_lat.dcm``); the same acquisitions as the plain subject of that seed. Returns the truth record."""
    subject = make_subject(seed, spacing_mm=spacing_mm)
    rng = np.random.default_rng([seed, 1])
    sample_injection(rng)  # drawn as write_phantom draws it, so the acquisitions are the plain case's
    nidus = add_nidus(subject, np.random.default_rng([seed, 11]))
    drr = _Opacified(dsa_renderer(subject, "arch"), DENSE_VESSEL_GAIN)
    acqs, iso = sample_biplane(rng, subject)
    sims = [simulate_dsa(subject, a, a.pose(iso), rng, injection="arch", drr=drr, max_matrix_px=max_matrix_px) for a in acqs]
    out.mkdir(parents=True, exist_ok=True)
    _write_volume(subject.cta, out / "cta.nii.gz", np.int16)
    _write_volume(subject.labels, out / "labels.nii.gz", np.uint8)
    lines = [{"name": c["name"], "label": c["label"], "points_mm": np.round(c["points_mm"], 3).tolist()}
             for c in subject.centerlines]
    (out / "centerlines.json").write_text(json.dumps({"frame": "centred native (RAS axes, origin at the CTA voxel-grid "
                                                      "centre), mm", "centerlines": lines}))
    views = {}
    for acq, sim, name in zip(acqs, sims, ("pa", "lat")):
        write_dsa_dicom(sim.run, out / f"dsa_{name}.dcm", bits=8, series_description=f"GeoPose dense phantom DSA {acq.view_role}")
        views[name] = {"file": f"dsa_{name}.dcm", "pose_camera_to_world": sim.pose.tolist(),
                       "primary_deg": acq.angles.primary_deg, "secondary_deg": acq.angles.secondary_deg}
    truth = subject.truth() | {"injection": "arch", "dense_vessel_gain": DENSE_VESSEL_GAIN, "nidus": nidus,
                               "isocentre_mm": iso.tolist(), "views": views}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seed_range, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--spacing-mm", type=float, default=1.0)
    args = ap.parse_args()
    for seed in args.seeds:
        write_dense_phantom(seed, args.out / f"dense-{seed}", spacing_mm=args.spacing_mm)
        print(f"dense-{seed} written", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
