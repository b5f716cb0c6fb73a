"""An oracle: the true patient pose joins the TTO tournament as a start (kept among the finalists). Where its run
ends lower by the objective than the default result, the search failed the default; where it ends higher, the
objective's optimum lies off the truth. Ran at 60a693c (session 43). Usage:

    .venv/bin/python experiments/tto_schedule/turned_starts/truth_start.py 6065,6080 OUT.jsonl
"""
from __future__ import annotations
import json, sys, tempfile
from pathlib import Path
import numpy as np
import geopose
from geopose.bench.cases import phantom_case
from geopose.metrics.measures import pose_error_components
from geopose.nets import load_models
from geopose.register import register_case, tournament as T
from geopose.register.biplane import nominal_poses, patient_pose
from geopose.register.evaluate import carotid_mpcd
from geopose.register.starts import DICOM_START

TRUTH = {}
orig_tried, orig_opt = T.tried_starts, T.optimise_from_starts
def tried(starts, count, estimate=None):
    out = orig_tried(starts, count, estimate); out["truth"] = TRUTH["X"]; return out
def opt(*a, keep=(), **k):
    return orig_opt(*a, keep=tuple(keep) + ("truth",), **k)
T.tried_starts, T.optimise_from_starts = tried, opt

def errs(case, poses):
    out = []
    for k in ("pa", "lat"):
        out.append(round(carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                                      case.carotid_points_mm)[0].detector_mm, 2))
    p = pose_error_components(poses["pa"], case.true_poses["pa"])
    return out + [round(float(np.hypot(p["in_plane_rotation_deg"], p["out_of_plane_rotation_deg"])), 2)]

models = load_models(runtime="torch")
out = open(sys.argv[2], "a")
for seed in [int(s) for s in sys.argv[1].split(",")]:
    with tempfile.TemporaryDirectory() as tmp:
        case = phantom_case(seed, Path(tmp), 2.0)
        rig = nominal_poses(case.runs)
        TRUTH["X"] = patient_pose(case.true_poses["pa"], rig["pa"])
        reg = register_case(case.cta, case.runs, models=models)
    r = reg.registration
    row = {"seed": seed, "chosen": r.chosen_start, "objectives": {k: round(v, 4) for k, v in r.tto_objective.items()},
           "runs": {k: errs(case, run.poses) for k, run in r.tto_runs.items()},
           "stopped": {k: run.stopped_at for k, run in r.tto_runs.items()},
           "final": errs(case, {k: reg.views[k].final_pose for k in ("pa", "lat")})}
    print(json.dumps(row), file=out, flush=True)
