"""The mirror test's two sides judged once more on vessels read again at each side's final pose, more strictly than
the tournament reads them at the networks' estimate (blur px / threshold per variant, a floor of 0.01 % passing).
Each held-out phantom is registered as a user does (``register_case``), its CTA as given and mirrored (array flipped
along the left-right axis, header kept); one JSON line per CTA: the product's margin, and per variant (margin, share
of the result's vessels kept, share of the mirrored hypothesis's).

    .venv/bin/python experiments/mirror/end_read.py --seeds 6010-6029 > rows.jsonl
"""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from heldout import heldout_phantoms  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case, mirror  # noqa: E402
from geopose.register import opacified as O  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose, view_poses  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.register.opacified import read_opacified, selection_judge  # noqa: E402
from geopose.register.tournament import Tournament  # noqa: E402
from geopose.register.tto import test_time_optimise, tto_views  # noqa: E402
from geopose.options import TTOSchedule  # noqa: E402
from geopose.render.renderer import TorchRenderer, make_renderer  # noqa: E402

#: (blur px, threshold) of the second reading; (2, 0.02) is the tournament's rule, read at the end.
VARIANTS = [(2.0, 0.02), (1.0, 0.1), (1.0, 0.2), (1.0, 0.3), (0.0, 0.3), (1.0, 0.5)]


def judged(volume, poses, views, rig, objective, engine, blur, thr):
    """The objective of ``poses`` on the vessels read at their patient pose with (``blur``, ``thr``), and the share kept."""
    O.OPACIFIED_BLUR_PX, O.OPACIFIED_THRESHOLD, O.OPACIFIED_MIN_FRACTION = blur, thr, 1e-4
    X = patient_pose(poses["pa"], rig["pa"])
    sel = read_opacified(volume, X, rig, [(k, views[k].tto_vessels, views[k].tto_detector) for k in views])
    O.OPACIFIED_BLUR_PX, O.OPACIFIED_THRESHOLD, O.OPACIFIED_MIN_FRACTION = 2.0, 0.02, 0.02
    judge = selection_judge(make_renderer(volume, engine, "cpu"), sel)
    return pair_objective(judge, poses, views, objective), (sel.kept_fraction if sel else None)


def mirror_ends(description: str):
    """Per held-out phantom and CTA (as given, then mirrored: the array flipped along the left-right axis, header kept)
    registered as a user does: ``(case, name, reg, work, result poses on it, mirrored volume, its 12-step TTO's run,
    prepared views, rig, objective)``, the mirror test's two ends rebuilt as ``register/mirror.py`` builds them."""
    models = load_models(runtime="torch")
    for args, case, out in heldout_phantoms(description, "6010-6029"):
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
            yield case, name, reg, work, res_poses, mvol, m, views, rig, objective, out


def main() -> None:
    for case, name, reg, work, res_poses, mvol, m, views, rig, objective, out in mirror_ends(__doc__.splitlines()[0]):
        row = {"case": case.name, "cta": name, "margin": reg.registration.mirror.margin}
        for blur, thr in VARIANTS:
            a, fa = judged(work, res_poses, views, rig, objective, reg.renderer.engine, blur, thr)
            b, fb = judged(mvol, m.poses, views, rig, objective, reg.renderer.engine, blur, thr)
            row[f"{blur}/{thr}"] = (b - a, fa, fb)
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
