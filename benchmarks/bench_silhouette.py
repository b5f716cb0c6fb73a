"""Which DRR the silhouette target is compared with (``Objective.silhouette`` /
``coarse_silhouette``): TTO (25 steps, one patient pose) started at the true pose of real head
CTs with simulated runs and of held-out phantoms, with

* the DRR clipped like the MAP at every step (the objective before 2026-12-03, session 26);
* the noise-level model fitted to the MAP at the full-size steps, the clipped DRR at the
  half-size ones (the default);
* the fitted model at every step.

A column that leaves the TTO at the truth has its optimum there.

    .venv/bin/python benchmarks/bench_silhouette.py --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --real-seeds 0-2 --seeds 5000-5005 --doc docs/silhouette.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_objective_real import case_errors  # noqa: E402
from heldout import publish  # noqa: E402

from geopose.bench.cases import BenchCase, ge_head_case, headsq_case, phantom_case, seed_range  # noqa: E402
from geopose.register.biplane import nominal_poses  # noqa: E402
from geopose.register.case import prepare_case  # noqa: E402
from geopose.register.objective import Objective  # noqa: E402
from geopose.register.pipeline import tto_views  # noqa: E402
from geopose.register.tto import test_time_optimise  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402

#: Column label -> the objective the TTO runs with.
MODELS = {
    "clipped DRR (before)": Objective(silhouette="clipped"),
    "fitted at full size (default)": Objective(),
    "fitted throughout": Objective(coarse_silhouette="fitted"),
}


def _cases(args: argparse.Namespace, tmp: Path):
    """The real-head cases (plain and with arteries), then the phantoms, built one at a time."""
    for path, make in ((args.headsq, headsq_case), (args.ge_head, ge_head_case)):
        for arteries in (False, True):
            for seed in (args.real_seeds if path else []):
                yield make(path, seed=seed, arteries=arteries)
    for seed in args.seeds:
        yield phantom_case(seed, tmp / str(seed), args.spacing_mm)


def _from_truth(case: BenchCase) -> list[tuple[float, float, float | None]]:
    """The errors of the TTO from the truth with each of :data:`MODELS`."""
    prep = prepare_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels)
    renderer, rig, views = TorchRenderer(prep.volume), nominal_poses(case.runs), tto_views(prep.views, case.true_poses)
    return [case_errors(case, test_time_optimise(renderer, views, rig=rig, objective=objective).poses)
            for objective in MODELS.values()]


def _cell(err: tuple[float, float, float | None]) -> str:
    rot, src, mpcd = err
    return f"{rot:.2f} / {src:.1f}" + ("" if mpcd is None else f" / {mpcd:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--headsq", help="headsq quarter_sidecar.mhd")
    ap.add_argument("--ge-head", help="the GE head CT DICOM folder")
    ap.add_argument("--real-seeds", type=seed_range, default=seed_range("0-2"), help="real-head case seeds, e.g. 0-2")
    ap.add_argument("--seeds", nargs="*", type=seed_range, default=[seed_range("5000-5005")],
                    help="held-out phantom seed ranges")
    ap.add_argument("--spacing-mm", type=float, default=2.0, help="phantom voxel spacing (mm)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=None, help="Markdown file to write the table to")
    args = ap.parse_args()
    args.seeds = [s for group in args.seeds for s in group]
    torch.set_num_threads(args.threads)
    rows: list[tuple[BenchCase, list]] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for case in _cases(args, Path(tmp)):
            cells = _from_truth(case)
            rows.append((case, cells))
            print(f"{case.name}: " + "; ".join(_cell(c) for c in cells) + f" ({(time.perf_counter() - t0) / 60:.1f} min)",
                  file=sys.stderr, flush=True)

    def summary(name: str, picked: list[list]) -> str:
        return f"| **{name}** | " + " | ".join(
            f"{np.mean([cells[i][0] for cells in picked]):.2f} / {max(cells[i][1] for cells in picked):.1f}"
            for i in range(len(MODELS))) + " |"

    groups = {
        "plain real heads: mean rotation / worst source": [c for case, c in rows if case.carotid_points_mm is None],
        "real heads with arteries: mean rotation / worst source": [
            c for case, c in rows if case.carotid_points_mm is not None and not case.name.startswith("phantom")],
        "phantoms: mean rotation / worst source": [c for case, c in rows if case.name.startswith("phantom")],
    }
    lines = ["| case | " + " | ".join(MODELS) + " |", "|---|" + "---:|" * len(MODELS)]
    lines += [f"| {case.name} | " + " | ".join(_cell(c) for c in cells) + " |" for case, cells in rows]
    lines += [summary(name, picked) for name, picked in groups.items() if picked]
    intro = ("python benchmarks/bench_silhouette.py " + " ".join(sys.argv[1:]) + "\n\n"
             "TTO (25 steps, one patient pose) started at the true pose, with each silhouette model. Per cell: the "
             "worst view's rotation error (deg) / source-position error (mm) [/ mean carotid mPCD (mm), cases with "
             "arteries]; 0 / 0: the optimum is at the truth.")
    publish("\n".join(lines), args.doc, "Which DRR the silhouette target is compared with", intro)
    return 0


if __name__ == "__main__":
    sys.exit(main())
