"""How many common-axis searches does the mirror test's short TTO need? Each held-out phantom is registered as a
user does (``register_case``, masks computed), its CTA as given and mirrored (the array flipped along the left-right
axis, header kept); the mirror test (``register/mirror.py``) is then run again on that registration's tournament and
networks' estimate with two searches (after 60 and 80 % of its steps), one (after 60 %) and none. Per variant: the
margin (mirrored hypothesis less result; below -``MIRROR_LOSS_MARGIN`` the result fails) and the test's seconds.

    .venv/bin/python experiments/mirror/axis_searches.py --seeds 6010-6029 --doc experiments/mirror/axis_searches_table.md
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
from geopose.register import register_case  # noqa: E402
from geopose.register import mirror  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.tournament import Tournament  # noqa: E402

VARIANTS = {"two searches": (0.6, 0.8), "one search": (0.6,), "none": ()}


def main() -> None:
    models = load_models(runtime="torch")
    rows, out, kept = [], sys.stdout, mirror.MIRROR_AXIS_SEARCH_AT
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):
        axis = 2 - int(np.argmax(np.abs(case.cta.ijk_to_ras[0, :3]) / np.asarray(case.cta.spacing_mm)))
        for name, cta in (("correct", case.cta), ("mirrored", case.cta.like(np.ascontiguousarray(np.flip(case.cta.array, axis))))):
            reg = register_case(cta, case.runs, models=models)
            r = reg.registration
            if r.mirror is None:
                continue
            rig = nominal_poses(case.runs)
            tournament = Tournament(r.tto_runs, r.tto_objective, r.chosen_start, r.vessel_selection)
            estimate = patient_pose(reg.views["pa"].search_pose, rig["pa"])
            views = {k: reg.views[k].prepared for k in ("pa", "lat")}
            row = {"case": case.name, "cta": name}
            for variant, at in VARIANTS.items():
                mirror.MIRROR_AXIS_SEARCH_AT = at
                t0 = time.perf_counter()
                test = mirror.mirror_test(reg.renderer, views, tournament, estimate, rig, reg.options.objective)
                row[variant] = (test.margin, time.perf_counter() - t0)
            mirror.MIRROR_AXIS_SEARCH_AT = kept
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    bar = mirror.MIRROR_LOSS_MARGIN
    lines = [f"Margin (fails below -{bar}) and seconds of the mirror test:", "",
             "| case | CTA | " + " | ".join(VARIANTS) + " |", "|---|---|" + "---:|" * len(VARIANTS)]
    lines += [f"| {row['case']} | {row['cta']} | " + " | ".join(f"{row[v][0]:+.3f} ({row[v][1]:.2f} s)" for v in VARIANTS) + " |"
              for row in rows]
    for cta in ("correct", "mirrored"):
        group = [row for row in rows if row["cta"] == cta]
        lines.append(f"\n{cta}: failed " + ", ".join(f"{v} {sum(row[v][0] < -bar for row in group)} of {len(group)}"
                                                      for v in VARIANTS))
    print("\n".join(lines), file=out, flush=True)


if __name__ == "__main__":
    main()
