"""The mirror test's two sides judged once more on vessels read again at each side's final pose and thinned by the
two-view emission fit (``experiments/vessel_mask/selection_fit/selection_mlem.py``): the tournament's lenient read
(2 px, 0.02), then the voxels whose MLEM weight reaches a share of the 90th percentile. As ``end_read.py``: each held-out
phantom registered as a user does, its CTA as given and mirrored; one JSON line per CTA: the product's margin and per
variant (margin, voxels kept by the result's read, by the mirrored hypothesis's).

    .venv/bin/python experiments/mirror/end_fit.py --seeds 6010-6012 6024-6029 > rows.jsonl
"""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "vessel_mask" / "selection_fit"))
from heldout import heldout_phantoms  # noqa: E402
from selection_mlem import mlem_weights  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case, mirror  # noqa: E402
from geopose.register import opacified as O  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose, view_poses  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.register.tournament import Tournament  # noqa: E402
from geopose.register.tto import test_time_optimise, tto_views  # noqa: E402
from geopose.options import TTOSchedule  # noqa: E402
from geopose.render.renderer import TorchRenderer, make_renderer  # noqa: E402

#: (MLEM blur px, share of the 90th percentile); None: the lenient read alone.
VARIANTS = [None, (0.7, 0.05), (1.0, 0.1), (0.7, 0.2)]


def judged(volume, poses, views, rig, objective, engine, fit):
    """The objective of ``poses`` on the vessels read at their patient pose (thinned by ``fit``), and the voxels kept."""
    X = patient_pose(poses["pa"], rig["pa"])
    images = [(k, views[k].tto_vessels, views[k].tto_detector) for k in views]
    sel = O.read_opacified(volume, X, rig, images)
    if sel is None or not sel.applied:
        return pair_objective(make_renderer(volume, engine, "cpu"), poses, views, objective), 0
    kept = sel.kept_kji
    if fit is not None:
        w = mlem_weights(volume.centred_points(kept), X, rig, [i for i in images if np.max(i[1]) > 0], fit[0])
        kept = kept[w >= fit[1] * np.percentile(w, 90)]
    judge = make_renderer(volume.with_vessels(kept), engine, "cpu")
    return pair_objective(judge, poses, views, objective), len(kept)


def main() -> None:
    models = load_models(runtime="torch")
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):
        axis = 2 - int(np.argmax(np.abs(case.cta.ijk_to_ras[0, :3]) / np.asarray(case.cta.spacing_mm)))
        for name, cta in (("correct", case.cta), ("mirrored", case.cta.like(np.ascontiguousarray(np.flip(case.cta.array, axis))))):
            reg = register_case(cta, case.runs, models=models)
            r = reg.registration
            if r.mirror is None:
                continue
            objective, rig = reg.options.objective, nominal_poses(case.runs)
            estimate = patient_pose(reg.views["pa"].search_pose, rig["pa"])
            views = {k: reg.views[k].prepared for k in ("pa", "lat")}
            work, shift = reg.renderer.volume.coarsened(mirror.work_factors(reg.renderer.volume))
            t = Tournament(r.tto_runs, r.tto_objective, r.chosen_start, r.vessel_selection)
            res_poses = {k: shift @ T for k, T in t.result.poses.items()}
            mvol = mirror.mirrored_volume(work, mirror.midsagittal_plane(work.cta))
            m = test_time_optimise(TorchRenderer(mvol, "cpu"), tto_views(views, view_poses(shift @ estimate, rig)),
                                   TTOSchedule(mirror.MIRROR_TTO_ITERATIONS, coarse_fraction=1.0, axis_search_at=(0.6,)),
                                   objective=objective, rig=rig)
            row = {"case": case.name, "cta": name, "margin": r.mirror.margin}
            for fit in VARIANTS:
                a, ka = judged(work, res_poses, views, rig, objective, reg.renderer.engine, fit)
                b, kb = judged(mvol, m.poses, views, rig, objective, reg.renderer.engine, fit)
                row["lenient" if fit is None else f"fit {fit[0]}/{fit[1]}"] = (round(b - a, 4), ka, kb)
            print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
