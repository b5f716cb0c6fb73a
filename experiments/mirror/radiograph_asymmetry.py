"""How differently do a head and its mirror image look in a plain radiograph (a native run's mask frame)? An oracle
at the true poses, to size a radiograph cue for the mirror test before building one: per view, the NCC of the
CTA's total-density DRR and of its mirror image's (reflected across the head's own midsagittal plane, as
``register/mirror.py`` reflects it) with the mask frame, over the DSA cranium mask. Phantoms are written with
``--native-runs`` (their mask frame: the phantom's own radiograph); the real heads' mask frame is their CT's DRR at
the true pose (the runs the benchmark simulates are stored subtracted). One JSON line per case.

    .venv/bin/python experiments/mirror/radiograph_asymmetry.py 6010-6019 --headsq ../shared/data/headsq/quarter_sidecar.mhd
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import geopose  # noqa: F401  (before torch)
import numpy as np
import pydicom

from geopose.bench.cases import ge_head_case, headsq_case, seed_range
from geopose.cta import load_cta
from geopose.cta.symmetry import midsagittal_plane
from geopose.dsa import read_dsa
from geopose.dsa.preprocess import resample_to_detector
from geopose.phantom.cli import write_phantom
from geopose.register import prepare_case
from geopose.register.mirror import mirrored_volume, work_factors
from geopose.render.renderer import TorchRenderer


def ncc(a: np.ndarray, b: np.ndarray, inside: np.ndarray) -> float:
    a, b = a[inside] - a[inside].mean(), b[inside] - b[inside].mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def measure(name: str, cta, runs, poses: dict, mask_frames: dict | None) -> dict:
    prep = prepare_case(cta, runs)
    work, shift = prep.volume.coarsened(work_factors(prep.volume))
    given, mirrored = TorchRenderer(work), TorchRenderer(mirrored_volume(work, midsagittal_plane(work.cta)))
    row = {"case": name}
    for key, view in prep.views.items():
        det = view.tto_detector
        pose = shift @ poses[key]
        drr = given.render(pose, det)[0]
        frame = drr if mask_frames is None else resample_to_detector(mask_frames[key], runs[key].detector, det)
        inside = view.tto_mask > 0
        row[key] = {"given": ncc(drr, frame, inside), "mirrored": ncc(mirrored.render(pose, det)[0], frame, inside),
                    "drr_vs_mirrored": ncc(drr, mirrored.render(pose, det)[0], inside)}
    return row


def native_mask_frame(path: Path) -> np.ndarray:
    ds = pydicom.dcmread(path)
    frames = ds.pixel_array.reshape(int(ds.NumberOfFrames), ds.Rows, ds.Columns).astype(np.float64)
    return -np.log(np.maximum(frames[int(ds.MaskSubtractionSequence[0].MaskFrameNumbers) - 1], 1.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seeds", type=seed_range)
    ap.add_argument("--spacing-mm", type=float, default=1.0)
    ap.add_argument("--headsq", type=Path)
    ap.add_argument("--ge-head", type=Path)
    args = ap.parse_args()
    for seed, path in ((0, args.headsq), (1, args.headsq), (0, args.ge_head)):
        if path is not None:
            case = (headsq_case if path == args.headsq else ge_head_case)(path, seed)
            print(json.dumps(measure(case.name, case.cta, case.runs, case.true_poses, None)), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            folder = Path(tmp) / str(seed)
            write_phantom(seed, folder, spacing_mm=args.spacing_mm, native_runs=True)
            truth = json.loads((folder / "truth.json").read_text())
            poses = {k: np.asarray(truth["views"][k]["pose_camera_to_world"]) for k in ("pa", "lat")}
            runs = {k: read_dsa(folder / f"dsa_{k}.dcm") for k in ("pa", "lat")}
            frames = {k: native_mask_frame(folder / f"dsa_{k}.dcm") for k in ("pa", "lat")}
            print(json.dumps(measure(f"phantom-{seed}", load_cta(folder / "cta.nii.gz"), runs, poses, frames)), flush=True)


if __name__ == "__main__":
    sys.exit(main())
