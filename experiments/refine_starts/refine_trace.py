"""Each greedy Refine start's course on the default path: per held-out phantom, each of the nine starts
(``starts.refine_starts``) refined alone (each start makes the same moves alone as in the lockstep), its
views' mean mNCC before and after every proposal step, its end's carotid mPCD per view, and the start the
lockstep keeps; the data for refining fewer starts (issue 33: Refine is half the time before the TTO).

    .venv/bin/python experiments/refine_starts/refine_trace.py --seeds 6010-6029 --doc /tmp/refine.jsonl
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.register.biplane import nominal_poses  # noqa: E402
from geopose.register.calibration import calibrate  # noqa: E402
from geopose.register.engine import start_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.init import biplane_init  # noqa: E402
from geopose.register.progress import Monitor  # noqa: E402
from geopose.register.refine import refine_from_starts  # noqa: E402
from geopose.register.starts import refine_starts  # noqa: E402


def course(trace_by_view: dict) -> list[float]:
    """The views' mean mNCC at the start and after each proposal (a retry is a proposal)."""
    keys = list(trace_by_view)
    first = trace_by_view[keys[0]]
    scores = [float(np.mean([trace_by_view[k].start_mncc for k in keys]))]
    current = scores[0]
    for i, p in enumerate(first.proposals):
        if p.accepted:
            current = float(np.mean([trace_by_view[k].proposals[i].mncc for k in keys]))
        scores.append(current)
    return scores


def main() -> None:
    models = load_models(runtime="torch")
    options = RegistrationOptions()
    for _, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):
        seed = int(case.name.split("-")[-1])
        engine, prepared = start_case(case.cta, case.runs, options, models, cranium_mask=None, segmentation=None,
                                      dsa_masks=None, monitor=Monitor())
        rig = nominal_poses(case.runs)
        calibration = calibrate(engine.renderer, models.init, engine.render_px)
        init = biplane_init(prepared, models.init, calibration, rig, Monitor())
        starts = refine_starts(init)
        targets, labels = prepared.model_targets(), prepared.view_labels()
        t0 = time.perf_counter()
        joint = refine_from_starts(engine.renderer, targets, starts, rig, labels, models.refine, engine.render_px,
                                   options.refine)
        seconds = time.perf_counter() - t0
        row = {"seed": seed, "kept": joint.start, "lockstep_s": round(seconds, 3), "starts": {}}
        for name, X in starts.items():
            alone = refine_from_starts(engine.renderer, targets, {name: X}, rig, labels, models.refine,
                                       engine.render_px, options.refine)
            mm = [round(carotid_mpcd(t.pose, case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                                     case.carotid_points_mm)[0].detector_mm, 3) for k, t in alone.traces.items()]
            row["starts"][name] = {"course": [round(s, 5) for s in course(alone.traces)], "mpcd_mm": mm,
                                   "proposals": len(alone.traces["pa"].proposals)}
        print(json.dumps(row), file=out, flush=True)

if __name__ == "__main__":
    main()
