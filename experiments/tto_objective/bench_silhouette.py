"""Which DRR the silhouette target is compared with (``Objective.silhouette`` /
``coarse_silhouette``): TTO (25 steps, one patient pose) started at the true pose of real head
CTs with simulated runs and of held-out phantoms, with

* the DRR clipped like the MAP at every step (the objective before 2026-12-03, session 26);
* the noise-level model fitted to the MAP at the full-size steps, the clipped DRR at the
  half-size ones (the default);
* the fitted model at every step.

A column that leaves the TTO at the truth has its optimum there.

    .venv/bin/python experiments/tto_objective/bench_silhouette.py --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --real-seeds 0-2 --seeds 5000-5005 --doc experiments/tto_objective/silhouette.md
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: heldout.py
from bench_objective_real import case_errors  # noqa: E402
from heldout import case_groups, case_table, publish, run_cases  # noqa: E402

from geopose.bench.cases import BenchCase  # noqa: E402
from geopose.register.biplane import nominal_poses  # noqa: E402
from geopose.register.case import prepare_case  # noqa: E402
from geopose.register.objective import Objective  # noqa: E402
from geopose.register.tto import tto_views  # noqa: E402
from geopose.register.tto import test_time_optimise  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402

#: Column label -> the objective the TTO runs with.
MODELS = {
    "clipped DRR (before)": Objective(silhouette="clipped"),
    "fitted at full size (default)": Objective(),
    "fitted throughout": Objective(coarse_silhouette="fitted"),
}


def _from_truth(case: BenchCase) -> list[tuple[float, float, float | None]]:
    """The errors of the TTO from the truth with each of :data:`MODELS`."""
    prep = prepare_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels)
    renderer, rig, views = TorchRenderer(prep.volume), nominal_poses(case.runs), tto_views(prep.views, case.true_poses)
    return [case_errors(case, test_time_optimise(renderer, views, rig=rig, objective=objective).poses)
            for objective in MODELS.values()]


def main() -> int:
    args, rows = run_cases(__doc__.splitlines()[0], "5000-5005", 2, _from_truth)
    lines = case_table(list(MODELS), rows)
    lines += [f"| **{name}: mean rotation / worst source** | " + " | ".join(
        f"{np.mean([cells[i][0] for cells in picked]):.2f} / {max(cells[i][1] for cells in picked):.1f}"
        for i in range(len(MODELS))) + " |" for name, picked in case_groups(rows).items()]
    intro = ("python experiments/tto_objective/bench_silhouette.py " + " ".join(sys.argv[1:]) + "\n\n"
             "TTO (25 steps, one patient pose) started at the true pose, with each silhouette model. Per cell: the "
             "worst view's rotation error (deg) / source-position error (mm) [/ mean carotid mPCD (mm), cases with "
             "arteries]; 0 / 0: the optimum is at the truth.")
    publish("\n".join(lines), args.doc, "Which DRR the silhouette target is compared with", intro)
    return 0


if __name__ == "__main__":
    sys.exit(main())
