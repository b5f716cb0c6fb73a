"""How far the TTO's OneCycle should anneal: the default registration (all starts, the tournament,
25 steps) with the patient-pose schedule's last learning rate set to several shares of its peak
(``TTOSchedule.final_lr_fraction``), on real head CTs with simulated runs and on held-out phantoms.
An anneal to ~0 (PyTorch's default, 1 / 250000) leaves the last full-size steps too little reach;
one that stays high leaves the result jittering about the optimum.

    .venv/bin/python benchmarks/bench_anneal.py --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --real-seeds 0-2 --seeds 5030-5031 5000-5005 --doc docs/tto_anneal.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from unittest import mock

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_objective_real import case_errors  # noqa: E402
from heldout import publish  # noqa: E402

from geopose import contract as C  # noqa: E402
from geopose.bench.cases import BenchCase, ge_head_case, headsq_case, phantom_case, seed_range  # noqa: E402
from geopose.register import pipeline  # noqa: E402
from geopose.register.case import VIEW_KEYS  # noqa: E402
from geopose.register.tto import TTOSchedule  # noqa: E402

FLOORS = (C.PAPER_TTO_FINAL_LR_FRACTION, 0.05, C.TTO_FINAL_LR_FRACTION, 0.25)


def _cases(args: argparse.Namespace, tmp: Path):
    """The real-head cases (plain and with arteries) and the phantoms, built one at a time."""
    for path, make in ((args.headsq, headsq_case), (args.ge_head, ge_head_case)):
        for arteries in (False, True):
            for seed in (args.real_seeds if path else []):
                yield make(path, seed=seed, arteries=arteries)
    for seed in args.seeds:
        yield phantom_case(seed, tmp / str(seed), args.spacing_mm)


def _register(case: BenchCase, floor: float) -> tuple[float, float, float | None]:
    """(worst view's rotation error deg, source-position error mm, mean carotid mPCD mm or None) of the
    default registration with the TTO annealing to ``floor`` of its peak learning rate."""
    with mock.patch.object(pipeline, "TTOSchedule", partial(TTOSchedule, final_lr_fraction=floor)):
        reg = pipeline.register_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels)
    return case_errors(case, {k: reg.views[k].final_pose for k in VIEW_KEYS})


def _cell(err: tuple[float, float, float | None]) -> str:
    rot, src, mpcd = err
    return f"{rot:.2f} / {src:.1f}" + ("" if mpcd is None else f" / {mpcd:.2f}")


def _label(floor: float) -> str:
    return f"{floor:.0e}" if floor < 0.01 else f"{floor:g}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--headsq", help="headsq quarter_sidecar.mhd")
    ap.add_argument("--ge-head", help="the GE head CT DICOM folder")
    ap.add_argument("--real-seeds", type=seed_range, default=seed_range("0-2"), help="real-head case seeds, e.g. 0-2")
    ap.add_argument("--seeds", nargs="*", type=seed_range, default=[seed_range("5030-5031"), seed_range("5000-5005")],
                    help="held-out phantom seed ranges")
    ap.add_argument("--spacing-mm", type=float, default=2.0, help="phantom voxel spacing (mm)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--doc", type=Path, default=None, help="Markdown file to write the table to")
    args = ap.parse_args()
    args.seeds = [s for group in args.seeds for s in group]
    torch.set_num_threads(args.threads)
    rows: list[tuple[BenchCase, list]] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for case in _cases(args, Path(tmp)):
            cells = [_register(case, floor) for floor in FLOORS]
            rows.append((case, cells))
            print(f"{case.name}: " + "; ".join(_cell(c) for c in cells) + f" ({(time.perf_counter() - t0) / 60:.1f} min)",
                  file=sys.stderr, flush=True)

    def summary(name: str, picked: list[list], what) -> str:
        return f"| **{name}** | " + " | ".join(what([cells[i] for cells in picked]) for i in range(len(FLOORS))) + " |"

    arteries = [cells for case, cells in rows if case.carotid_points_mm is not None and not case.name.startswith("phantom")]
    plain = [cells for case, cells in rows if case.carotid_points_mm is None]
    phantoms = [cells for case, cells in rows if case.name.startswith("phantom")]
    lines = ["| case | " + " | ".join(f"anneal to {_label(f)} of the peak" for f in FLOORS) + " |",
             "|---|" + "---:|" * len(FLOORS)]
    lines += [f"| {case.name} | " + " | ".join(_cell(c) for c in cells) + " |" for case, cells in rows]
    if arteries:
        lines.append(summary("real heads with arteries: worst source (mm), mean rotation (deg)", arteries,
                             lambda c: f"{max(x[1] for x in c):.1f}, {np.mean([x[0] for x in c]):.2f}"))
    if plain:
        lines.append(summary("plain real heads: worst source (mm), mean rotation (deg)", plain,
                             lambda c: f"{max(x[1] for x in c):.1f}, {np.mean([x[0] for x in c]):.2f}"))
    if phantoms:
        lines.append(summary("phantoms: mean mPCD (mm)", phantoms, lambda c: f"{np.mean([x[2] for x in c]):.2f}"))
    intro = ("python benchmarks/bench_anneal.py " + " ".join(sys.argv[1:]) + "\n\n"
             "The default registration (every start, the tournament, 25 TTO steps) with the OneCycle of the patient "
             "pose's TTO annealing to a share of its peak learning rate. Per cell: the worst view's rotation error (deg) "
             "/ source-position error (mm) [/ mean carotid mPCD (mm), cases with arteries].")
    publish("\n".join(lines), args.doc, "How far the TTO's learning rate anneals", intro)
    return 0


if __name__ == "__main__":
    sys.exit(main())
