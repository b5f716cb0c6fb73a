"""The default registration (``register_case`` with the CTA and the two runs, masks computed) with one more stage
after the TTO (and its continuation): the opacified vessels read again at the result and thinned by the two-view
emission fit of ``selection_mlem.py``, one more TTO run from the result on them, and every finalist judged by that
selection (as ``register/continuation.py`` judges). One JSON line per validation seed
(``turned_starts/default_path_rows.py``); compare with ``experiments/tto_schedule/turned_starts/compare.py``.

    .venv/bin/python experiments/vessel_mask/selection_fit/refit_pipeline.py --blur 0.7 --share 0.05 --seeds 6030-6049 --out OUT.jsonl
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from selection_mlem import keeping, mlem_weights, pipeline_parser  # noqa: E402  (geopose before torch)
import default_path_rows  # noqa: E402
from default_path_rows import run_seeds  # noqa: E402

from geopose.options import TTOSchedule  # noqa: E402
from geopose.register import opacified, pipeline, tto  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.register.tournament import Tournament, chosen_result  # noqa: E402

ap = pipeline_parser(__doc__.splitlines()[0], 0.7)
ap.add_argument("--iterations", type=int, default=25)
ap.add_argument("--coarse", type=float, default=0.6)
ap.add_argument("--axis", type=float, nargs="*", default=[0.6, 0.8])
ap.add_argument("--read-at-truth", action="store_true", help="oracle: the refit's read at the true pose")
ap.add_argument("--jitter-mm", type=float, default=0.0,
                help="the fit's weights averaged over the read pose and its isocentre moved +-this along each axis")
ap.add_argument("--rounds", type=int, default=1, help="refit runs, each reading at the last one's end")
args = ap.parse_args()
info: dict = {}
lenient_read = opacified.read_opacified


def fitted_read(volume, patient, rig, views, **kwargs):
    if args.read_at_truth:
        patient = truth["X"]
    selection = lenient_read(volume, patient, rig, views, **kwargs)
    if selection is None or not selection.applied:
        return selection
    images = [(n, im, det) for n, im, det in views if np.max(im) > 0]
    points = volume.centred_points(selection.kept_kji)
    moves = [np.zeros(3)] + [sign * args.jitter_mm * np.eye(3)[a] for a in range(3) for sign in (-1, 1)] \
        if args.jitter_mm > 0 else [np.zeros(3)]
    w = 0.0
    for move in moves:
        moved = np.array(patient, dtype=np.float64)
        moved[:3, 3] += move
        fit = mlem_weights(points, moved, rig, images, args.blur)
        w = w + fit / np.percentile(fit, 90)
    kept = selection.kept_kji[w >= args.share * np.percentile(w, 90)]
    info["read"] = [len(selection.kept_kji), len(kept)]
    return keeping(selection, volume, kept)


original_continued = pipeline.continued
truth: dict = {}
original_case = default_path_rows.phantom_case


def captured_case(*a, **k):
    case = original_case(*a, **k)
    rig = nominal_poses(case.runs)
    truth["X"] = patient_pose(case.true_poses["pa"], rig["pa"])
    return case


default_path_rows.phantom_case = captured_case


def continued_then_refit(renderer, tto_renderer, views, tournament, rig, schedule, objective, monitor=None):
    tournament = original_continued(renderer, tto_renderer, views, tournament, rig, schedule, objective, monitor)
    t0 = time.perf_counter()
    tto.read_opacified = fitted_read
    try:
        refit = TTOSchedule(args.iterations, coarse_fraction=args.coarse, axis_search_at=tuple(args.axis))
        poses = tournament.result.poses
        for _ in range(args.rounds):
            run = tto.test_time_optimise(tto_renderer, tto.tto_views(views, poses), refit, objective=objective, rig=rig)
            poses = run.poses
    finally:
        tto.read_opacified = lenient_read
    if run.vessel_selection is None or not run.vessel_selection.applied:
        info["refit"] = "no selection"
        return tournament
    judge = opacified.selection_judge(renderer, run.vessel_selection)
    runs = {**tournament.runs, "refit": run}
    objectives = {name: pair_objective(judge, r.poses, views, objective) for name, r in runs.items() if r.stopped_at is None}
    info["refit_objectives"] = {k: round(v, 4) for k, v in objectives.items()}
    info["refit_s"] = round(time.perf_counter() - t0, 2)
    return Tournament(runs, objectives, chosen_result(objectives), run.vessel_selection)


pipeline.continued = continued_then_refit
run_seeds(list(args.seeds), args.out,
          f"refit blur {args.blur} share {args.share} it {args.iterations} coarse {args.coarse} axis {args.axis} "
          f"rounds {args.rounds} jitter {args.jitter_mm}" + (" read at the truth (oracle)" if args.read_at_truth else ""), info)
