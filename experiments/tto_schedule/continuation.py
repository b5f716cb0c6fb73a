"""Does a TTO result that turned far from the networks' estimate arrive? Each held-out phantom is registered as a user
does (``register_case``, masks computed; run at commit 3bbce0f, before ``register/continuation.py``), then one more
default TTO (25 steps) runs from the registration's result. One JSON line per case: how far the result turned from the
networks' estimate (deg), carotid mPCD PA / LAT (mm) and rotation error (deg) of the result and of the second run, both
judged by the vessels the second run read (objective, both views summed), and how far the second run turned.

    .venv/bin/python experiments/tto_schedule/continuation.py --seeds 6010-6030 --doc rows.jsonl
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.continuation import turn_deg  # noqa: E402
from geopose.register.engine import torch_renderer_for  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.register.opacified import selection_judge  # noqa: E402
from geopose.register.tto import TTOSchedule, test_time_optimise, tto_views  # noqa: E402


def main() -> None:
    models = load_models(runtime="torch")
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6030"):
        reg = register_case(case.cta, case.runs, models=models)
        rig = nominal_poses(case.runs)
        prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
        X_result = reg.registration.patient_pose
        X_estimate = patient_pose(reg.views["pa"].search_pose, rig["pa"])
        X_true = patient_pose(case.true_poses["pa"], rig["pa"])

        def errors(poses: dict) -> list[float]:
            return [round(carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                                       case.carotid_points_mm)[0].detector_mm, 2) for k in ("pa", "lat")]

        first = {k: X_result @ rig[k] for k in rig}
        second = test_time_optimise(torch_renderer_for(reg.renderer), tto_views(prepared, first), TTOSchedule(), rig=rig)
        judge = selection_judge(reg.renderer, second.vessel_selection)
        row = {"case": case.name, "turn_from_estimate_deg": round(turn_deg(X_result, X_estimate), 1),
               "first": errors(first), "first_rot": round(turn_deg(X_result, X_true), 1),
               "second": errors(second.poses), "second_rot": round(turn_deg(second.patient_pose, X_true), 1),
               "judged": [round(pair_objective(judge, first, prepared), 4), round(pair_objective(judge, second.poses, prepared), 4)],
               "second_turn_deg": round(turn_deg(second.patient_pose, X_result), 1),
               "quality": [reg.views[k].quality.flag for k in ("pa", "lat")]}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
