"""Drift of the default TTO started at the truth (masks computed, as ``selection_oracle.py``) with the opacified read's
tolerance varied: its blur (px at the TTO size) and threshold (share of the vessel image's maximum). One JSON line per
seed. The "selection" counts are the last read that was applied (a read under ``OPACIFIED_MIN_FRACTION`` leaves the
previous variant's). Ran at 60a693c (session 43). Usage, from the repository root:

    .venv/bin/python experiments/vessel_mask/read_tolerance.py 6020 6028 OUT.jsonl
"""
from __future__ import annotations
import json, sys, tempfile
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from selection_oracle import OracleRead, ARTERIES, VEINS, DROPPED  # noqa
from geopose.bench.cases import phantom_case
from geopose.cta.io import load_cta
from geopose.metrics.measures import pose_error_components
from geopose.nets import load_models
from geopose.options import RegistrationOptions
from geopose.register import opacified, register_case, tto
from geopose.register.biplane import nominal_poses, patient_pose
from geopose.register.engine import torch_renderer_for
from geopose.register.evaluate import carotid_mpcd
from geopose.register.tto import TTOSchedule, test_time_optimise, tto_views

VARIANTS = {"2px 0.02": (2.0, 0.02), "1px 0.02": (1.0, 0.02), "1px 0.1": (1.0, 0.1), "1px 0.3": (1.0, 0.3),
            "2px 0.3": (2.0, 0.3), "0.7px 0.3": (0.7, 0.3)}
seeds = range(int(sys.argv[1]), int(sys.argv[2]) + 1)
models = load_models(runtime="torch")
options = RegistrationOptions().replace(**{"tto.iterations": 0})
read = OracleRead(); tto.read_opacified = read
out = open(sys.argv[3], "a")
for seed in seeds:
    with tempfile.TemporaryDirectory() as tmp:
        case = phantom_case(seed, Path(tmp), 2.0)
        read.labels = load_cta(Path(tmp) / "labels.nii.gz", check_hu=False).array
        rig = nominal_poses(case.runs)
        X = patient_pose(case.true_poses["pa"], rig["pa"])
        reg = register_case(case.cta, case.runs, models=models, options=options)
        prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
        row = {"case": case.name}
        for name, (blur, thr) in VARIANTS.items():
            opacified.OPACIFIED_BLUR_PX, opacified.OPACIFIED_THRESHOLD = blur, thr
            result = test_time_optimise(torch_renderer_for(reg.renderer), tto_views(prepared, {k: X @ rig[k] for k in rig}),
                                        TTOSchedule(25), rig=rig)
            parts = pose_error_components(result.poses["pa"], case.true_poses["pa"])
            row[name] = {"drift_mm": [round(carotid_mpcd(result.poses[k], case.true_poses[k], case.runs[k].detector,
                                                         case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm, 3)
                                      for k in ("pa", "lat")],
                         "rotation_deg": round(float(np.hypot(parts["in_plane_rotation_deg"], parts["out_of_plane_rotation_deg"])), 3),
                         "selection": dict(read.composition)}
        print(json.dumps(row), file=out, flush=True)
