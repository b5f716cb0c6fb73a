"""The default path on phantoms written at a given voxel size: how much does the CTA's resolution change the result?

Each folder is a phantom case as ``geopose phantom --seed S --spacing-mm MM --out DIR/S`` writes it (``cta.nii.gz``,
``dsa_pa.dcm``, ``dsa_lat.dcm`` and the truth beside them). Each is registered as a user does (``register_case`` with
the CTA and the two runs read from the files, masks computed, every option at its default); the truth only scores. One
JSON line per case: carotid mPCD (mm at the detector) and rotation error (deg) per view of the result and of the
networks' estimate, the start kept, whether the networks' estimate was kept, the mirror test's margin, the flags and
the total time (s). ``--set NAME=VALUE`` registers with an option away from its default. ``--mirrored``: the CTA's array flipped along its left-right axis, the header kept (as
``experiments/mirror/mirror_default_path.py``): the mirror test should fail the result.

    for s in $(seq 6010 6034); do geopose phantom --seed $s --spacing-mm 1 --out /tmp/ph1/$s; done
    .venv/bin/python experiments/resolution/resolution.py --folders /tmp/ph1 --seeds 6010-6034 --doc rows_1mm.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
from types import SimpleNamespace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import flipped_left_right, view_errors  # noqa: E402  (also puts the library on the path, geopose before torch)

from geopose.bench.cases import seed_range, training_seeds  # noqa: E402
from geopose.cta.io import load_cta  # noqa: E402
from geopose.dsa.readers import read_dsa  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import load_truth  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402


def estimate_pose(view):
    """The networks' estimate of a view: after the similarity search, or after greedy Refine where it did not run."""
    return view.search_pose if view.search_pose is not None else view.refine.pose


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folders", type=Path, required=True, help="the folder holding one phantom case folder per seed")
    ap.add_argument("--seeds", type=seed_range, required=True, help="held-out seeds, e.g. 6010-6034")
    ap.add_argument("--doc", type=Path, default=None, help="JSON lines out (default: stdout)")
    ap.add_argument("--mirrored", action="store_true", help="register each CTA mirrored left-right")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a registration option away from its default, e.g. estimate_voxel_per_pixel=3 (repeatable)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    clash = training_seeds(default_models_dir() / "manifest.json") & set(args.seeds)
    if clash:
        raise SystemExit(f"seeds {sorted(clash)} were used to train the shipped models: choose held-out seeds")
    models = load_models(runtime="torch")
    options = RegistrationOptions().replace(**{k: json.loads(v) for k, v in (a.split("=", 1) for a in args.set)})
    out = open(args.doc, "w") if args.doc else sys.stdout
    for seed in args.seeds:
        folder = args.folders / str(seed)
        cta = load_cta(folder / "cta.nii.gz")
        if args.mirrored:
            cta = flipped_left_right(cta)
        runs = {"pa": read_dsa(folder / "dsa_pa.dcm"), "lat": read_dsa(folder / "dsa_lat.dcm")}
        truth = load_truth(folder / "cta.nii.gz")
        scored = SimpleNamespace(true_poses=truth.poses, runs=runs, carotid_points_mm=truth.carotid_points_mm)
        reg = register_case(cta, runs, models=models, options=options)
        r = reg.registration
        row = {"seed": seed, "final": view_errors(scored, {k: reg.views[k].final_pose for k in runs}),
               "estimate": view_errors(scored, {k: estimate_pose(reg.views[k]) for k in runs}),
               "chosen": r.chosen_start, "kept_learned": bool(r.kept_learned),
               "mirror": None if r.mirror is None else round(float(r.mirror.margin), 4),
               "flags": [reg.views[k].quality.flag for k in ("pa", "lat")], "total_s": round(reg.runtimes_s["total"], 2),
               "runtimes_s": {k: round(v, 2) for k, v in reg.runtimes_s.items()}}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
