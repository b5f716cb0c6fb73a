"""What the tournament's two runs look like after the coarse steps, on the default path: per held-out phantom
(``register_case`` with the CTA and the two runs) each start's full-size loss after the coarse steps, its final
objective, that loss's pose judged as the finalists are, the carotid mPCD of its result, how far apart the two runs' poses lie there (mPCD of one against the
other), and the start chosen; the data for stopping a run that cannot win (issue 33).

    .venv/bin/python experiments/tto_schedule/tournament_trace.py --seeds 6010-6029 --doc /tmp/tournament.jsonl
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import parse_heldout_args  # noqa: E402

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register import pipeline  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.register.opacified import selection_judge  # noqa: E402

_run_tournament = pipeline.run_tournament
#: Per start, its pose after the coarse steps judged by the tournament's final judge (the last registration's).
COARSE_JUDGED: dict[str, float] = {}


def _judged_tournament(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, **kw):
    """The pipeline's tournament, and each run's first full-size pose judged as the finalists are."""
    tournament = _run_tournament(renderer, tto_renderer, views, starts, rig, schedule, objective, monitor, **kw)
    judge = selection_judge(renderer, tournament.vessel_selection)
    COARSE_JUDGED.clear()
    for name, run in tournament.runs.items():
        first = next(t for t in run.trace if t["size"] == "full")
        COARSE_JUDGED[name] = pair_objective(judge, {k: np.asarray(v["pose"]) for k, v in first["views"].items()}, views, objective)
    return tournament


pipeline.run_tournament = _judged_tournament


def main() -> None:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "6010-6029")
    models = load_models(runtime="torch")
    out = open(args.doc, "w") if args.doc else sys.stdout
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            case = phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm)
            reg = register_case(case.cta, case.runs, models=models)
            r = reg.registration

            def mpcd(poses: dict, against: dict | None = None) -> list[float]:
                ref = against or case.true_poses
                return [carotid_mpcd(np.asarray(poses[k]), np.asarray(ref[k]), case.runs[k].detector, case.runs[k].angles.sod_mm,
                                     case.carotid_points_mm)[0].detector_mm for k in ("pa", "lat")]

            runs = {}
            coarse_poses = {}
            for name, run in r.tto_runs.items():
                full = [t for t in run.trace if t["size"] == "full"]
                first = full[0] if full else None
                coarse_poses[name] = {k: v["pose"] for k, v in first["views"].items()} if first else None
                runs[name] = {"coarse_loss": first["loss"] if first else None, "coarse_iteration": first["iteration"] if first else None,
                              "final_objective": r.tto_objective.get(name), "mpcd_mm": mpcd(run.poses),
                              "coarse_mpcd_mm": mpcd(coarse_poses[name]) if first else None,
                              "coarse_judged": COARSE_JUDGED.get(name)}
            names = list(runs)
            apart = mpcd(coarse_poses[names[0]], coarse_poses[names[1]]) if len(names) == 2 else None
            row = {"seed": seed, "starts": r.starts, "chosen": r.chosen_start, "runs": runs, "coarse_apart_mm": apart,
                   "final_mpcd_mm": mpcd({k: v.final_pose for k, v in reg.views.items()}),
                   "flags": [reg.views[k].quality.flag for k in ("pa", "lat")],
                   "mirror_margin": None if r.mirror is None else r.mirror.margin, "runtimes_s": reg.runtimes_s}
            print(json.dumps(row, default=float), file=out, flush=True)


if __name__ == "__main__":
    main()
