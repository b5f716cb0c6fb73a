"""Should the continuation run on again while its run keeps turning?

One case: ``CASE_FOLDER`` (e.g. benchmark 5030 as `geopose bench` writes it:
``geopose.bench.cases.phantom_case(5030, DIR, 1.0)``) registered with the continuation repeated up to 1 (the product),
2 and 3 times; per N the final mPCD / rotation error per view, the chosen start, the runs' objectives, the total time.
A sweep: ``--seeds A-B --runs N --minutes M`` registers held-out phantoms (written as the benchmark writes them) with
up to N continued runs and, where a second one ran, with the product too; one JSON line per case to ``--out``.

    .venv/bin/python experiments/tto_schedule/continuation_repeat.py CASE_FOLDER
    .venv/bin/python experiments/tto_schedule/continuation_repeat.py --seeds 6035-6099 --runs 2 --minutes 30 --out rows.jsonl
"""
import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))
import geopose  # noqa: E402,F401  (before torch)
import torch  # noqa: E402

from geopose.bench.cases import phantom_case, seed_range  # noqa: E402
from geopose.cta import load_cta  # noqa: E402
from geopose.dsa import read_dsa  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import continuation as C, pipeline  # noqa: E402
from geopose.register.evaluate import load_truth, truth_metrics  # noqa: E402
from geopose.register.tournament import Tournament, chosen_result  # noqa: E402

REAL = C.continued


def repeated(n: int):
    """``continuation.continued`` run up to ``n`` times, each from the last continued run's end while it wins and turns."""
    def cont(renderer, tto_renderer, views, tournament, rig, schedule, objective, monitor=None):
        for i in range(n):
            before = tournament
            tournament = REAL(renderer, tto_renderer, views, tournament, rig, schedule, objective, monitor)
            if tournament is before or tournament.chosen != C.CONTINUED_START:
                break
            if i + 1 < n:  # rename the continued run so that the next one can take the name
                runs = dict(tournament.runs)
                runs[f"continued {i + 1}"] = runs.pop(C.CONTINUED_START)
                objectives = dict(tournament.objectives)
                objectives[f"continued {i + 1}"] = objectives.pop(C.CONTINUED_START)
                tournament = Tournament(runs, objectives, chosen_result(objectives), tournament.vessel_selection)
        return tournament
    return cont


def register(models, folder: Path, n: int) -> dict:
    pipeline.continued = repeated(n)
    cta = load_cta(folder / "cta.nii.gz")
    runs = {k: read_dsa(folder / f"dsa_{k}.dcm") for k in ("pa", "lat")}
    r = pipeline.register_case(cta, runs, models=models)
    m = truth_metrics(r, runs, load_truth(folder / "cta.nii.gz"))
    return {"mpcd_mm": [round(m[k]["final"]["mpcd_mm"], 3) for k in ("pa", "lat")],
            "rotation_deg": round(m["pa"]["final"]["rotation_error_deg"], 3), "chosen": r.registration.chosen_start,
            "runs": sorted(r.registration.tto_runs), "flags": [r.views[k].quality.flag for k in ("pa", "lat")],
            "objectives": {k: round(v, 4) for k, v in r.registration.tto_objective.items()},
            "total_s": round(r.runtimes_s["total"], 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("case", nargs="?", type=Path)
    ap.add_argument("--seeds", type=seed_range)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(2)
    models = load_models()
    if args.case is not None:
        for n in (1, 2, 3):
            print(n, json.dumps(register(models, args.case, n)), flush=True)
        return
    stop = time.monotonic() + 60.0 * args.minutes
    for seed in args.seeds:
        if time.monotonic() > stop:
            break
        with tempfile.TemporaryDirectory() as tmp:
            phantom_case(seed, Path(tmp) / "case", 1.0)
            row = {"seed": seed, f"up_to_{args.runs}": register(models, Path(tmp) / "case", args.runs)}
            if sum(name.startswith(C.CONTINUED_START) for name in row[f"up_to_{args.runs}"]["runs"]) > 1:  # ran on
                row["product"] = register(models, Path(tmp) / "case", 1)
        print(json.dumps(row), flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
