"""Does a longer ray-marching step cost accuracy? Each held-out phantom is registered as a user does
(``register_case``, masks computed) with ``render.renderer.TOTAL_STEP_VOXELS`` (the step of renders of the total
density alone: greedy Refine, the search, calibration) set to ``--total-factor`` and every DRR's step multiplied by
``--all-factor``. Runs on branch ``render-cells`` (867feb2), where that constant and the kernels' step argument exist
(not kept on main: render_step.md). One JSON line per case: carotid mPCD PA / LAT (mm) and rotation error (deg) of
the networks' estimate and of the result, the quality flags and the stage times (s).

    .venv/bin/python experiments/render_step/render_step.py --seeds 6010-6030 --total-factor 1.5 --doc rows.jsonl
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

FACTORS = {"total": 1.0, "all": 1.0}
for flag in ("total", "all"):
    opt = f"--{flag}-factor"
    if opt in sys.argv:
        i = sys.argv.index(opt)
        FACTORS[flag] = float(sys.argv[i + 1])
        del sys.argv[i:i + 2]

from heldout import heldout_phantoms  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.continuation import turn_deg  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.render import renderer  # noqa: E402
from geopose.render.drr import DRR  # noqa: E402

renderer.TOTAL_STEP_VOXELS = FACTORS["total"]
_forward = DRR.forward


def _stepped(self, pose, detector=None, channels=None, step_mm=None):
    return _forward(self, pose, detector, channels, (step_mm or self.step_mm) * FACTORS["all"])


DRR.forward = _stepped


def main() -> None:
    models = load_models(runtime="torch")
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6030"):
        reg = register_case(case.cta, case.runs, models=models)
        rig = nominal_poses(case.runs)
        X_true = patient_pose(case.true_poses["pa"], rig["pa"])

        def errors(poses: dict) -> list[float]:
            return [round(carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                                       case.carotid_points_mm)[0].detector_mm, 3) for k in ("pa", "lat")]

        X_est = patient_pose(reg.views["pa"].search_pose, rig["pa"])
        X_res = reg.registration.patient_pose
        row = {"case": case.name, "factors": FACTORS,
               "estimate": errors({k: X_est @ rig[k] for k in rig}), "estimate_rot": round(turn_deg(X_est, X_true), 2),
               "result": errors({k: X_res @ rig[k] for k in rig}), "result_rot": round(turn_deg(X_res, X_true), 2),
               "chosen": reg.registration.chosen_start,
               "quality": [reg.views[k].quality.flag for k in ("pa", "lat")],
               "mirror_margin": None if reg.registration.mirror is None else round(reg.registration.mirror.margin, 4),
               "runtimes_s": {k: round(v, 2) for k, v in reg.runtimes_s.items()}}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
