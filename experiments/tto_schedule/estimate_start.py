"""Does the TTO need the networks' estimate among its starts when another start scores better? Each held-out
phantom is registered as a user does (``register_case``, masks computed) up to the TTO's candidate starts; where a
start other than the estimate (greedy Refine + search) has the lowest objective besides the DICOM angles, the case
is registered in full twice: with the tournament's starts as before session 39 (the DICOM angles and the best other
by objective) and as now (the estimate too, ``tournament.tried_starts``).

    .venv/bin/python experiments/tto_schedule/estimate_start.py --seeds 6010-6099 --doc experiments/tto_schedule/estimate_start_table.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

import geopose.register.tournament as tournament  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.starts import DICOM_START, SEARCHED_START  # noqa: E402

NOW = tournament.tried_starts
RULES = {"before (best other only)": lambda starts, count, estimate=None: NOW(starts, count, None),
         "now (the estimate too)": NOW}


def main() -> None:
    models = load_models(runtime="torch")
    screened, rows, out = 0, [], sys.stdout
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6099"):
        screened += 1
        starts = register_case(case.cta, case.runs, models=models,
                               options=RegistrationOptions().replace(**{"tto.iterations": 0})).registration.starts
        others = sorted((k for k in starts if k != DICOM_START), key=starts.get)
        print(json.dumps({"case": case.name, "starts": starts}, default=float), file=sys.stderr, flush=True)
        if not others or others[0] == SEARCHED_START:
            continue
        row = {"case": case.name, "best_other": others[0]}
        for rule, picker in RULES.items():
            tournament.tried_starts = picker
            reg = register_case(case.cta, case.runs, models=models)
            row[rule] = ([carotid_mpcd(reg.views[k].final_pose, case.true_poses[k], case.runs[k].detector,
                                       case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm for k in ("pa", "lat")],
                         [reg.views[k].quality.flag for k in ("pa", "lat")], reg.runtimes_s["tto"])
        tournament.tried_starts = NOW
        rows.append(row)
    lines = [f"{screened} phantoms screened; {len(rows)} had a start other than the networks' estimate of lowest objective "
             "(besides the DICOM angles). Carotid mPCD PA / LAT (mm), flags, TTO stage (s):", "",
             "| case | best other start | " + " | ".join(RULES) + " |", "|---|---|" + "---|" * len(RULES)]
    for row in rows:
        cells = [f"{m[0]:.2f} / {m[1]:.2f} ({f[0]}, {f[1]}; {t:.1f} s)" for m, f, t in (row[r] for r in RULES)]
        lines.append(f"| {row['case']} | {row['best_other']} | " + " | ".join(cells) + " |")
    print("\n".join(lines), file=out, flush=True)


if __name__ == "__main__":
    main()
