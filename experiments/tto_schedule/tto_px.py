"""The TTO's image size on a CPU: per held-out phantom, the default registration (``register_case`` with the CTA and the
two runs) with the TTO rendering at each size of ``SIZES`` (pixels along the detector's longer side; its coarse steps
and the mirror test at half that); each one's final carotid mPCD and rotation error per view, flags and stage times
(issue 33: the whole registration in 10 s on 2 cores).

    .venv/bin/python experiments/tto_schedule/tto_px.py --seeds 6010-6029 --doc /tmp/tto_px.jsonl
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.metrics.measures import pose_errors  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions, TTOSchedule  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402

#: TTO image sizes compared (the CPU default first).
SIZES = (128, 96)


def main() -> None:
    models = load_models(runtime="torch")
    for _, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):
        row = {"seed": int(case.name.split("-")[-1])}
        for px in SIZES:
            reg = register_case(case.cta, case.runs, models=models, options=RegistrationOptions(tto=TTOSchedule(px=px)))
            poses = {k: v.final_pose for k, v in reg.views.items()}
            row[str(px)] = {
                "mpcd_mm": [round(carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector,
                                               case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm, 3)
                            for k in ("pa", "lat")],
                "rotation_deg": [round(float(pose_errors(poses[k][None], case.true_poses[k][None]).rotation_deg[0]), 3)
                                 for k in ("pa", "lat")],
                "flags": [reg.views[k].quality.flag for k in ("pa", "lat")],
                "t": {k: round(v, 2) for k, v in reg.runtimes_s.items()}}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
