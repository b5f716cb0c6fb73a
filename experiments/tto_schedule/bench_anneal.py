"""How far the TTO's OneCycle should anneal: the default registration (all starts, the tournament,
25 steps) with the patient-pose schedule's last learning rate set to several shares of its peak
(``TTOSchedule.final_lr_fraction``), on real head CTs with simulated runs and on held-out phantoms.
An anneal to ~0 (PyTorch's default, 1 / 250000) leaves the last full-size steps too little reach;
one that stays high leaves the result jittering about the optimum.

    .venv/bin/python experiments/tto_schedule/bench_anneal.py --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --real-seeds 0-2 --seeds 5030-5031 5000-5005 --doc experiments/tto_schedule/tto_anneal.md
"""

from __future__ import annotations

import sys
from functools import partial
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tto_objective"))  # bench_objective_real.py
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: heldout.py
from bench_objective_real import case_errors  # noqa: E402
from heldout import case_groups, case_table, publish, run_cases  # noqa: E402

from geopose.bench.cases import BenchCase  # noqa: E402
from geopose.register import pipeline  # noqa: E402
from geopose.register.case import VIEW_KEYS  # noqa: E402
from geopose.register.tto import PAPER_SCHEDULE, TTOSchedule  # noqa: E402

FLOORS = (PAPER_SCHEDULE.final_lr_fraction, 0.05, TTOSchedule.final_lr_fraction, 0.25)


def _register(case: BenchCase, floor: float) -> tuple[float, float, float | None]:
    """(worst view's rotation error deg, source-position error mm, mean carotid mPCD mm or None) of the
    default registration with the TTO annealing to ``floor`` of its peak learning rate."""
    with mock.patch.object(pipeline, "TTOSchedule", partial(TTOSchedule, final_lr_fraction=floor)):
        reg = pipeline.register_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels)
    return case_errors(case, {k: reg.views[k].final_pose for k in VIEW_KEYS})


def _label(floor: float) -> str:
    return f"{floor:.0e}" if floor < 0.01 else f"{floor:g}"


def main() -> int:
    args, rows = run_cases(__doc__.splitlines()[0], "5030-5031 5000-5005", 1,
                           lambda case: [_register(case, floor) for floor in FLOORS])

    def summary(name: str, picked: list[list], what) -> str:
        return f"| **{name}** | " + " | ".join(what([cells[i] for cells in picked]) for i in range(len(FLOORS))) + " |"

    lines = case_table([f"anneal to {_label(f)} of the peak" for f in FLOORS], rows)
    for name, picked in case_groups(rows).items():
        if name == "phantoms":
            lines.append(summary("phantoms: mean mPCD (mm)", picked, lambda c: f"{np.mean([x[2] for x in c]):.2f}"))
        else:
            lines.append(summary(f"{name}: worst source (mm), mean rotation (deg)", picked,
                                 lambda c: f"{max(x[1] for x in c):.1f}, {np.mean([x[0] for x in c]):.2f}"))
    intro = ("python experiments/tto_schedule/bench_anneal.py " + " ".join(sys.argv[1:]) + "\n\n"
             "The default registration (every start, the tournament, 25 TTO steps) with the OneCycle of the patient "
             "pose's TTO annealing to a share of its peak learning rate. Per cell: the worst view's rotation error (deg) "
             "/ source-position error (mm) [/ mean carotid mPCD (mm), cases with arteries].")
    publish("\n".join(lines), args.doc, "How far the TTO's learning rate anneals", intro)
    return 0


if __name__ == "__main__":
    sys.exit(main())
