"""The networks' estimate (greedy Refine + search, the TTO switched off) on validation phantoms: its rotation error
split into the turn about the axis both image planes contain and the rest, for it and for the DICOM angles.
Ran at 60a693c (session 43). Usage, from the repository root:

    .venv/bin/python experiments/tto_schedule/turned_starts/estimate_error.py 6030 6099 OUT.jsonl
"""
import json, sys, tempfile
from pathlib import Path
import numpy as np
import geopose
from geopose.bench.cases import phantom_case
from geopose.nets import load_models
from geopose.options import RegistrationOptions
from geopose.register import register_case
from geopose.register.biplane import nominal_poses, patient_pose, common_axis
from geopose.geometry.poses import matrix_to_axis_angle
models = load_models(runtime="torch")
opts = RegistrationOptions().replace(**{"tto.iterations": 0})
out = open(sys.argv[3], "a")
for seed in range(int(sys.argv[1]), int(sys.argv[2]) + 1):
    with tempfile.TemporaryDirectory() as tmp:
        case = phantom_case(seed, Path(tmp), 2.0)
        reg = register_case(case.cta, case.runs, models=models, options=opts)
    rig = nominal_poses(case.runs)
    Xt = patient_pose(case.true_poses["pa"], rig["pa"])
    axis = common_axis({k: Xt for k in rig}, rig)
    row = {"seed": seed}
    for name, X in (("estimate", patient_pose(reg.views["pa"].search_pose, rig["pa"])), ("dicom", np.eye(4))):
        turn = np.degrees(matrix_to_axis_angle(Xt[:3, :3] @ X[:3, :3].T))
        along = float(turn @ axis)
        row[name] = {"total_deg": round(float(np.linalg.norm(turn)), 2), "common_axis_deg": round(along, 2),
                     "other_deg": round(float(np.linalg.norm(turn - along * axis)), 2), "shift_mm": round(float(np.linalg.norm(X[:3, 3] - Xt[:3, 3])), 1)}
    print(json.dumps(row), file=out, flush=True)
