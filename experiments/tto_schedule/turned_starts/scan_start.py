"""The default path with a single-pose scan along the common-axis valley before the TTO (every 4 deg within +-16,
the vessels read opacified at each turn): the best turn replaces the networks' estimate (``replace``), or
joins the starts (``extra``). Ran at 60a693c (session 43); not kept. Usage:

    .venv/bin/python experiments/tto_schedule/turned_starts/scan_start.py 6030,6031 OUT.jsonl replace|extra 4
"""
import json, sys, tempfile, time
from pathlib import Path
import numpy as np
import geopose
from geopose.bench.cases import phantom_case
from geopose.nets import load_models
from geopose.register import register_case, pipeline
from geopose.register.biplane import nominal_poses, patient_pose, view_poses, moved_by
from geopose.register.axis_search import valley_turn
from geopose.register.objective import pair_objective
from geopose.register.opacified import read_opacified, selection_judge
from geopose.register.starts import Starts
from geopose.register.evaluate import carotid_mpcd
from geopose.metrics.measures import pose_error_components
MODE = sys.argv[3]  # replace | extra
STEP = float(sys.argv[4]) if len(sys.argv) > 4 else 2.0
TURNS = np.arange(-16, 16.01, STEP)
INFO = {}
orig = pipeline.run_tournament
def scanned(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, *, estimate=None):
    t0 = time.perf_counter()
    name, X = estimate
    vol = renderer.volume
    kji = vol.mask_voxels("vessels")
    if MODE != "none" and len(kji):
        pts = vol.centred_points(kji[:: max(1, len(kji) // 2000)])
        direction = valley_turn(X, rig, {k: views[k].tto_detector for k in rig}, pts)
        vv = [(k, views[k].tto_vessels, views[k].tto_detector) for k in rig]
        scores = []
        for t in TURNS:
            Y = moved_by(X, direction[0] * np.radians(t), direction[1] * np.radians(t))
            sel = read_opacified(vol, Y, rig, vv)
            scores.append(pair_objective(selection_judge(renderer, sel), view_poses(Y, rig), views, objective))
        i = int(np.argmin(scores))
        INFO["turn"] = float(TURNS[i]); INFO["gain"] = scores[len(TURNS) // 2] - scores[i]
        if TURNS[i] != 0:
            Xs = moved_by(X, direction[0] * np.radians(TURNS[i]), direction[1] * np.radians(TURNS[i]))
            key = name if MODE == "replace" else "scan"
            poses = dict(starts.poses); objs = dict(starts.objectives)
            poses[key] = Xs; objs[key] = pair_objective(renderer, view_poses(Xs, rig), views, objective)
            starts = Starts(poses, objs)
            X = Xs if MODE == "replace" else X
    INFO["scan_s"] = time.perf_counter() - t0
    return orig(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, estimate=(name, X))
pipeline.run_tournament = scanned
from geopose.register import tournament as T  # noqa: E402
orig_tried = T.tried_starts
def tried(starts, count, estimate=None):
    out = orig_tried(starts, count, estimate)
    if "scan" in starts.poses:  # the extra variant: the scanned start always runs
        out["scan"] = starts.poses["scan"]
    return out
T.tried_starts = tried

def errs(case, poses):
    out = {}
    for k in ("pa", "lat"):
        m = carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm
        p = pose_error_components(poses[k], case.true_poses[k])
        out[k] = (round(m, 3), round(float(np.hypot(p["in_plane_rotation_deg"], p["out_of_plane_rotation_deg"])), 3))
    return out
models = load_models(runtime="torch")
out = open(sys.argv[2], "a")
for seed in [int(s) for s in sys.argv[1].split(",")]:
    INFO.clear()
    with tempfile.TemporaryDirectory() as tmp:
        case = phantom_case(seed, Path(tmp), 2.0)
        reg = register_case(case.cta, case.runs, models=models)
    r = reg.registration
    row = {"seed": seed, "mode": MODE, "kept_learned": bool(r.kept_learned), "chosen": r.chosen_start,
           "tto_objective": r.tto_objective, "final": errs(case, {k: reg.views[k].final_pose for k in ("pa", "lat")}),
           "flags": {k: reg.views[k].quality.flag for k in ("pa", "lat")}, "total_s": round(reg.runtimes_s["total"], 2),
           "tto_s": round(reg.runtimes_s.get("tto", 0), 2), **INFO}
    print(json.dumps(row), file=out, flush=True)
