"""The objective along the common-axis valley (``axis_search.valley_turn``) at single poses, turns -16..+16 deg in
2-deg steps, from the networks' estimate (``estimate``) or from the default registration's result (``result``):
the rotation error at each turn and three scores (the objective with every vessel, with the vessels read opacified at
that turn, the silhouette alone). Ran at 60a693c (session 43). Usage:

    .venv/bin/python experiments/tto_schedule/turned_starts/valley_scan.py 6080,6068 OUT.jsonl estimate|result
"""
import json, sys, tempfile
from pathlib import Path
import numpy as np
import geopose
from geopose.bench.cases import phantom_case
from geopose.nets import load_models
from geopose.options import RegistrationOptions, Objective
from geopose.register import register_case
from geopose.register.biplane import nominal_poses, patient_pose, view_poses, moved_by
from geopose.register.axis_search import valley_turn
from geopose.register.objective import pair_objective
from geopose.register.opacified import read_opacified, selection_judge
from geopose.metrics.measures import pose_error_components
models = load_models(runtime="torch")
AT = sys.argv[3]
opts = RegistrationOptions().replace(**{"tto.iterations": 0}) if AT == "estimate" else RegistrationOptions()
SIL = Objective(vessel_weight=0.0)
TURNS = np.arange(-16, 17, 2.0)
out = open(sys.argv[2], "a")
for seed in [int(s) for s in sys.argv[1].split(",")]:
    with tempfile.TemporaryDirectory() as tmp:
        case = phantom_case(seed, Path(tmp), 2.0)
        reg = register_case(case.cta, case.runs, models=models, options=opts)
    rig = nominal_poses(case.runs)
    renderer = reg.renderer
    prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
    X = patient_pose(reg.views["pa"].search_pose, rig["pa"]) if AT == "estimate" else reg.registration.patient_pose
    vol = renderer.volume
    kji = vol.mask_voxels("vessels")
    pts = vol.centred_points(kji[:: max(1, len(kji) // 2000)])
    direction = valley_turn(X, rig, {k: prepared[k].tto_detector for k in rig}, pts)
    row = {"seed": seed, "rot": [], "all": [], "sel": [], "sil": [], "kept": []}
    for t in TURNS:
        Y = moved_by(X, direction[0] * np.radians(t), direction[1] * np.radians(t))
        poses = view_poses(Y, rig)
        p = pose_error_components(poses["pa"], case.true_poses["pa"])
        row["rot"].append(round(float(np.hypot(p["in_plane_rotation_deg"], p["out_of_plane_rotation_deg"])), 2))
        row["all"].append(round(pair_objective(renderer, poses, prepared), 4))
        row["sil"].append(round(pair_objective(renderer, poses, prepared, SIL), 4))
        views = [(k, prepared[k].tto_vessels, prepared[k].tto_detector) for k in rig]
        sel = read_opacified(vol, Y, rig, views)
        row["kept"].append(None if sel is None else round(sel.kept_fraction, 3))
        row["sel"].append(round(pair_objective(selection_judge(renderer, sel), poses, prepared), 4))
    print(json.dumps(row), file=out, flush=True)
