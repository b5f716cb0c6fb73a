"""``geopose phantom``: write one phantom subject with a biplane DSA pair."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from pydicom.uid import generate_uid

from ..dsa import write_dsa_dicom
from ..volume import Volume
from .avm import PATHOLOGIES
from .dsa import DENSE_RUNS, INJECTIONS, RUNS, dsa_renderer, injected_arteries, opacified_labels, sample_biplane, sample_injection, simulate_dsa
from .subject import make_subject
from ..errors import InputError

__all__ = ["register", "write_phantom", "written_injected_arteries"]

OUTPUT_FILES = ("cta.nii.gz", "labels.nii.gz", "centerlines.json", "truth.json", "dsa_pa.dcm", "dsa_lat.dcm")


def _write_volume(vol: Volume, path: Path, dtype) -> None:
    """NIfTI via SimpleITK (which stores LPS direction/origin; the file is RAS-correct)."""
    img = sitk.GetImageFromArray(np.ascontiguousarray(vol.array.astype(dtype)))
    m = vol.ijk_to_ras
    spacing = np.linalg.norm(m[:3, :3], axis=0)
    lps = np.diag([-1.0, -1.0, 1.0]) @ m[:3, :3] / spacing
    img.SetSpacing(spacing.tolist())
    img.SetDirection(lps.flatten().tolist())
    img.SetOrigin((np.diag([-1.0, -1.0, 1.0]) @ m[:3, 3]).tolist())
    sitk.WriteImage(img, str(path), useCompression=True, compressionLevel=1)


def write_phantom(seed: int, out: Path, *, spacing_mm: float = 1.0, injection: str | None = None, max_matrix_px: int = 1024,
                  pathology: str | None = None, native_runs: bool = False) -> dict:
    """Generate subject ``seed`` and write the six files into ``out``; returns timings (s).

    ``injection``: one of ``dsa.RUNS`` (default: a routine catheter position drawn from the seed);
    ``pathology``: ``"avm"`` draws the subject with an arteriovenous malformation (implied by the
    ``"avm"`` run). ``native_runs``: the runs unsubtracted, as angiography systems archive them (a mask frame first,
    16-bit X-ray intensities, a Mask Subtraction Sequence that subtracts them; same seed, same subtracted runs but for
    8-bit rounding and burnt-in text). ``truth.json`` records all three, the AVM and the label values the runs fill."""
    pathology = pathology or (DENSE_RUNS[injection].pathology if injection in DENSE_RUNS else None)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    subject = make_subject(seed, spacing_mm=spacing_mm, pathology=pathology)
    timings["volume_s"] = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 1])
    injection = injection or sample_injection(rng)
    t1 = time.perf_counter()
    drr = dsa_renderer(subject, injection)
    acqs, iso = sample_biplane(rng, subject)
    runs = [simulate_dsa(subject, a, a.pose(iso), rng, injection=injection, drr=drr, max_matrix_px=max_matrix_px, native=native_runs)
            for a in acqs]
    timings["dsa_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    _write_volume(subject.cta, out / "cta.nii.gz", np.int16)
    _write_volume(subject.labels, out / "labels.nii.gz", np.uint8)
    lines = [
        {"name": c["name"], "label": c["label"], "points_mm": np.round(c["points_mm"], 3).tolist(), "radii_mm": np.round(c["radii_mm"], 3).tolist(),
         "lumen_hu": np.round(c["lumen_hu"]).tolist()}
        for c in subject.centerlines
    ]
    (out / "centerlines.json").write_text(json.dumps({"frame": "centred native (RAS axes, origin at the CTA voxel-grid centre), mm", "centerlines": lines}))
    views = {}
    study = generate_uid(entropy_srcs=["geopose-phantom", str(seed)])  # one biplane acquisition: one study
    for acq, sim, name in zip(acqs, runs, ("pa", "lat")):
        write_dsa_dicom(sim.run, out / f"dsa_{name}.dcm", bits=16 if native_runs else 8, study_instance_uid=study,
                        series_description=f"GeoPose phantom DSA {acq.view_role}{' (native)' if native_runs else ''}",
                        mask_subtraction=sim.subtraction)
        views[name] = {
            "file": f"dsa_{name}.dcm",
            "pose_camera_to_world": sim.pose.tolist(),
            "pose_frame": "centred native CTA frame (mm), docs/conventions.md sections 1-2",
            "table_rotation": np.round(acq.table_rotation, 9).tolist(),
            "table_rotation_doc": "3x3 from the angiography table's axes (those of the DICOM angles) to the native frame",
            "primary_deg": acq.angles.primary_deg, "secondary_deg": acq.angles.secondary_deg,
            "sid_mm": acq.angles.sid_mm, "sod_mm": acq.angles.sod_mm,
            "acquired_matrix_px": list(acq.detector.shape), "written_matrix_px": list(sim.run.detector.shape),
            "pixel_spacing_mm": list(sim.run.detector.spacing_mm), "frames": acq.n_frames, "frame_time_ms": acq.frame_time_ms,
            "native": native_runs, "mask_frames": 1 if native_runs else 0,
            "carotid_centerlines_px": {k: np.round(v, 2).tolist() for k, v in sim.carotids.items()},
        }
    early, late, venous = opacified_labels(injection)
    truth = subject.truth() | {"injection": injection, "opacified_labels": {"early": early, "late": late, "venous": venous},
                               "isocentre_mm": iso.tolist(), "views": views}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    timings["write_s"] = time.perf_counter() - t2
    timings["total_s"] = time.perf_counter() - t0
    return timings


def written_injected_arteries(folder: Path) -> np.ndarray:
    """``[k, j, i]`` bool on the CTA grid: the arteries the runs of a phantom folder written by
    :func:`write_phantom` show filled (its labels and ``truth.json``'s injection; an oracle)."""
    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(Path(folder) / "labels.nii.gz")))
    return injected_arteries(labels, json.loads((Path(folder) / "truth.json").read_text())["injection"])


def _run(args: argparse.Namespace) -> int:
    if args.spacing_mm < 0.5:
        raise InputError(f"--spacing-mm must be at least 0.5 mm, got {args.spacing_mm}")
    t = write_phantom(args.seed, Path(args.out), spacing_mm=args.spacing_mm, injection=args.injection, max_matrix_px=args.max_matrix_px,
                      pathology=args.pathology, native_runs=args.native_runs)
    print(f"phantom seed {args.seed} -> {args.out}: " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("phantom", help="write a phantom head CTA, labels, centerlines, truth and a biplane DSA pair")
    p.add_argument("--seed", type=int, default=0, help="subject seed (same seed, same files)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--spacing-mm", type=float, default=1.0, help="isotropic voxel size (mm, >= 0.5); 256 mm field of view")
    p.add_argument("--injection", choices=RUNS, default=None,
                   help=f"catheter position ({', '.join(sorted(INJECTIONS))}; default: one drawn from the seed) or a densely "
                   "opacified run: all_territories (every artery, both sides, strong contrast), avm (an AVM's nidus with early "
                   "venous drainage; implies --pathology avm), late_venous (the sinuses filled with the arteries)")
    p.add_argument("--pathology", choices=PATHOLOGIES, default=None,
                   help="draw the subject with a pathology: avm (a nidus fed by an M2 branch, draining into the sagittal sinus)")
    p.add_argument("--max-matrix-px", type=int, default=1024, help="cap on the written DSA matrix (px); the field of view is kept")
    p.add_argument("--native-runs", action="store_true",
                   help="write the runs unsubtracted, as angiography systems archive them: a mask frame, then the live "
                   "frames, with the Mask Subtraction Sequence that subtracts them (16-bit, about twice the size)")
    p.set_defaults(func=_run)
