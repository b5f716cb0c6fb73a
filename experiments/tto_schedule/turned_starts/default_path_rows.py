"""The loop the pipeline variants share: each validation phantom registered as a user does (``register_case`` with
the CTA and the two runs, masks computed), one JSON line per seed: the start chosen, the TTO's objectives, the final
carotid mPCD (mm) and rotation error (deg) per view, the flags and the time (s), with the variant's own ``info``."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from geopose.bench.cases import phantom_case
from geopose.metrics.measures import pose_error_components
from geopose.nets import load_models
from geopose.register import register_case
from geopose.register.evaluate import carotid_mpcd


def view_errors(case, poses) -> dict:
    """Per view: (carotid mPCD at the detector, mm; rotation error, deg) of ``poses`` against the phantom's truth."""
    out = {}
    for k in ("pa", "lat"):
        m = carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                         case.carotid_points_mm)[0].detector_mm
        p = pose_error_components(poses[k], case.true_poses[k])
        out[k] = (round(m, 3), round(float(np.hypot(p["in_plane_rotation_deg"], p["out_of_plane_rotation_deg"])), 3))
    return out


def run_seeds(seeds: list[int], out_path: str, mode: str, info: dict) -> None:
    """Register each seed (2 mm phantoms, default options) and append its row to ``out_path``; ``info`` is filled by
    the variant's patch during the registration and cleared before each."""
    models = load_models(runtime="torch")
    with open(out_path, "a") as out:
        for seed in seeds:
            info.clear()
            with tempfile.TemporaryDirectory() as tmp:
                case = phantom_case(seed, Path(tmp), 2.0)
                reg = register_case(case.cta, case.runs, models=models)
            r = reg.registration
            row = {"seed": seed, "mode": mode, "kept_learned": bool(r.kept_learned), "chosen": r.chosen_start,
                   "tto_objective": r.tto_objective,
                   "final": view_errors(case, {k: reg.views[k].final_pose for k in ("pa", "lat")}),
                   "flags": {k: reg.views[k].quality.flag for k in ("pa", "lat")},
                   "total_s": round(reg.runtimes_s["total"], 2), "tto_s": round(reg.runtimes_s.get("tto", 0), 2), **info}
            print(json.dumps(row), file=out, flush=True)
