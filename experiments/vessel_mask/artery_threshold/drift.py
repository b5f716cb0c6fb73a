"""How far the default TTO started at the truth drifts (the benchmark's drift row) with the CTA vessel mask made by
each variant of the rule: the artery classifier's cut (p >= 0.5 or 0.3) and the canal-mouth bridge on or off. One JSON
line per case and variant: carotid mPCD (mm at the detector) of the TTO's end per view, and the mask's voxel precision
and carotid centreline recall against the phantom (scoring only).

    .venv/bin/python experiments/vessel_mask/artery_threshold/drift.py --folders /tmp/ph1 --seeds 6010-6024 --doc rows.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from heldout import view_errors  # noqa: E402  (puts the library on the path, geopose before torch)

import numpy as np  # noqa: E402

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.cta import arteries, masks  # noqa: E402
from geopose.cta.io import load_cta  # noqa: E402
from geopose.dsa.readers import read_dsa  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.engine import torch_renderer_for  # noqa: E402
from geopose.register.evaluate import load_truth  # noqa: E402
from geopose.register.tto import TTOSchedule, test_time_optimise, tto_views  # noqa: E402

VARIANTS = {"p0.5": (0.5, False), "p0.3": (0.3, False), "mouths p0.5": (0.5, True), "mouths p0.3": (0.3, True)}


def variant_mask(cta, threshold: float, mouths: bool) -> np.ndarray:
    """The computed vessel mask ([k, j, i] bool) with the classifier's cut at ``threshold`` and the canal-mouth bridge
    on or off (``masks`` patched for the call only)."""
    bridge, load = masks._canal_mouths, masks.load_artery_classifier
    try:
        if not mouths:
            masks._canal_mouths = lambda tree, canal, *a: (np.zeros_like(canal),) * 2
        masks.load_artery_classifier = lambda: dataclasses.replace(load(), threshold=threshold)
        return masks.vessel_mask_from_cta(cta).array > 0
    finally:
        masks._canal_mouths, masks.load_artery_classifier = bridge, load


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folders", type=Path, required=True)
    ap.add_argument("--seeds", type=seed_range, required=True)
    ap.add_argument("--iterations", type=int, default=25)
    ap.add_argument("--doc", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    options = RegistrationOptions().replace(**{"tto.iterations": 0})
    out = open(args.doc, "w") if args.doc else sys.stdout
    for seed in args.seeds:
        folder = args.folders / str(seed)
        cta = load_cta(folder / "cta.nii.gz")
        arteries_true = L.vessel_mask(load_cta(folder / "labels.nii.gz", check_hu=False).array) > 0
        runs = {"pa": read_dsa(folder / "dsa_pa.dcm"), "lat": read_dsa(folder / "dsa_lat.dcm")}
        truth = load_truth(folder / "cta.nii.gz")
        scored = dataclasses.make_dataclass("Scored", ["true_poses", "runs", "carotid_points_mm"])(
            truth.poses, runs, truth.carotid_points_mm)
        rig = nominal_poses(runs)
        X = patient_pose(truth.poses["pa"], rig["pa"])
        row = {"seed": seed}
        for name, (threshold, mouths) in VARIANTS.items():
            mask = variant_mask(cta, threshold, mouths)
            reg = register_case(cta, runs, models=models, options=options, segmentation=cta.like(mask.astype(np.uint8)))
            prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
            result = test_time_optimise(torch_renderer_for(reg.renderer), tto_views(prepared, {k: X @ rig[k] for k in rig}),
                                        TTOSchedule(args.iterations), rig=rig)
            row[name] = {"drift": view_errors(scored, result.poses),
                         "precision": round(float((mask & arteries_true).sum() / max(mask.sum(), 1)), 3)}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
