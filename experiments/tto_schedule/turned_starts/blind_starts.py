"""The default path with the networks' estimate turned -STEP and +STEP deg along the common-axis valley added to the
TTO's starts (the prototype of ``starts.turned_starts``; ran at 60a693c, before the product did this itself, so on
later commits these starts would be added twice). Usage:

    .venv/bin/python experiments/tto_schedule/turned_starts/blind_starts.py 6080,6068 OUT.jsonl blind 8
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
MODE = sys.argv[3]  # blind | keep-estimate (the estimate's run also runs to the end)
STEP = float(sys.argv[4]) if len(sys.argv) > 4 else 2.0
TURNS = np.arange(-16, 16.01, STEP)
INFO = {}
orig = pipeline.run_tournament
def scanned(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, *, estimate=None):
    t0 = time.perf_counter()
    name, X = estimate
    vol = renderer.volume
    kji = vol.mask_voxels("vessels")
    if len(kji):
        pts = vol.centred_points(kji[:: max(1, len(kji) // 2000)])
        direction = valley_turn(X, rig, {k: views[k].tto_detector for k in rig}, pts)
        poses = dict(starts.poses); objs = dict(starts.objectives)
        for t in (-STEP, STEP):
            Xs = moved_by(X, direction[0] * np.radians(t), direction[1] * np.radians(t))
            poses[f"scan {t:+g}"] = Xs; objs[f"scan {t:+g}"] = pair_objective(renderer, view_poses(Xs, rig), views, objective)
        starts = Starts(poses, objs)
    INFO["scan_s"] = time.perf_counter() - t0
    return orig(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, estimate=(name, X))
pipeline.run_tournament = scanned
from geopose.register import tournament as T
orig_tried = T.tried_starts
def tried(starts, count, estimate=None):
    out = orig_tried(starts, count, estimate)
    out.update({k: X for k, X in starts.poses.items() if k.startswith("scan")})
    return out
T.tried_starts = tried
KEEP_ESTIMATE = MODE == "keep-estimate"  # the estimate's run is a finalist too (three finalists)
orig_opt = T.optimise_from_starts
def optimise(renderer, views, starts, rig, schedule, *, keep=(), **k):
    if KEEP_ESTIMATE and k.get("read_at") and k["read_at"][0] in starts:
        from dataclasses import replace
        keep = tuple(keep) + (k["read_at"][0],)
        schedule = replace(schedule, finalists=max(schedule.finalists, len(keep) + 1))
    return orig_opt(renderer, views, starts, rig, schedule, keep=keep, **k)
T.optimise_from_starts = optimise

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
