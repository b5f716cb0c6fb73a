"""Should the continuation run on again while its run keeps turning? One phantom folder (e.g. benchmark 5030 as
`geopose bench` writes it: `geopose.bench.cases.phantom_case(5030, DIR, 1.0)`), registered with the continuation
repeated up to 1 (the product), 2 and 3 times; per N the final mPCD / rotation error per view, the chosen start, the
runs' objectives and the total time.

    .venv/bin/python experiments/tto_schedule/continuation_repeat.py CASE_FOLDER
"""
import sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))
import geopose
import torch; torch.set_num_threads(2)
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.nets import load_models
from geopose.register import register_case, pipeline
from geopose.register import continuation as C
from geopose.register.evaluate import load_truth, truth_metrics
models = load_models()
d = sys.argv[1]
cta = load_cta(f"{d}/cta.nii.gz"); runs = {k: read_dsa(f"{d}/dsa_{k}.dcm") for k in ("pa", "lat")}
truth = load_truth(f"{d}/cta.nii.gz")
real = C.continued
def repeated(n):
    def cont(renderer, tto_renderer, views, tournament, rig, schedule, objective, monitor=None):
        for i in range(n):
            before = tournament
            tournament = real(renderer, tto_renderer, views, tournament, rig, schedule, objective, monitor)
            if tournament is before:
                break
            if i + 1 < n:  # the continued run becomes the start of the next: rename it so a new one can be added
                runs_ = dict(tournament.runs); run = runs_.pop(C.CONTINUED_START); runs_[f"continued {i + 1}"] = run
                obj = dict(tournament.objectives); o = obj.pop(C.CONTINUED_START, None)
                if o is not None: obj[f"continued {i + 1}"] = o
                from geopose.register.tournament import Tournament, chosen_result
                tournament = Tournament(runs_, obj, chosen_result(obj), tournament.vessel_selection)
                print("  continuation", i + 1, {k: round(v, 3) for k, v in obj.items()}, flush=True)
        return tournament
    return cont
for n in (1, 2, 3):
    pipeline.continued = repeated(n)
    r = register_case(cta, runs, models=models)
    m = truth_metrics(r, runs, truth)
    print(n, {k: (round(m[k]["final"]["mpcd_mm"], 2), round(m[k]["final"]["rotation_error_deg"], 2)) for k in ("pa", "lat")},
          r.registration.chosen_start, {k: round(v, 3) for k, v in r.registration.tto_objective.items()}, round(r.runtimes_s["total"], 1), flush=True)
