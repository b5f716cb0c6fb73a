"""Which part of the objective tells a mirrored CTA? Each held-out phantom is registered as a user does
(``register_case``, masks computed), its CTA as given and mirrored (array flipped along the left-right axis, header
kept). The mirror test's two sides are then taken apart per view and per term (silhouette mNCC, Dice loss, vessel
NCC): the result judged on the work grid (as ``mirror_test`` judges it), the mirrored hypothesis after its short TTO,
and a third, the CTA as given after the same short TTO from the same estimate (equal effort on both sides).
One JSON line per CTA. ``GEOPOSE_ORACLE_VESSELS`` hands a vessel segmentation in (mirrored with the CTA): ``truth``
the phantom's arteries, ``computed_arteries`` the computed mask's artery voxels alone, ``computed_plus_arteries`` the
computed mask with every artery added; oracles (upper bounds), not the user's path.

    .venv/bin/python experiments/mirror/terms.py --seeds 6010-6029 > rows.jsonl
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.cta import vessel_mask_from_cta  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import TTOSchedule  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register import mirror  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose, view_poses  # noqa: E402
from geopose.register.objective import objective_value  # noqa: E402
from geopose.register.opacified import selection_judge  # noqa: E402
from geopose.register.tournament import Tournament  # noqa: E402
from geopose.register.tto import test_time_optimise, tto_views  # noqa: E402
from geopose.render.renderer import TorchRenderer, make_renderer  # noqa: E402
from geopose.render.volume import coarse_mask  # noqa: E402


ORACLE = os.environ.get("GEOPOSE_ORACLE_VESSELS", "")


def oracle_vessels(cta, arteries):
    """The segmentation handed in for ``ORACLE`` (None: computed by the registration, the user's path)."""
    if not ORACLE:
        return None
    if ORACLE == "truth":
        return arteries
    computed, truth = vessel_mask_from_cta(cta).array > 0, arteries.array > 0
    return arteries.like((computed & truth if ORACLE == "computed_arteries" else computed | truth).astype(np.uint8))


def terms(judge, poses, views, objective) -> dict:
    out = {}
    for k in views:
        v = objective_value(judge, poses[k], views[k], objective)
        out[k] = [v.loss, v.mncc, v.dice_loss, v.vessel_ncc]
    return out


def short_tto(volume, views, estimate, shift, rig, objective, engine):
    result = test_time_optimise(TorchRenderer(volume, "cpu"), tto_views(views, view_poses(shift @ estimate, rig)),
                                TTOSchedule(mirror.MIRROR_TTO_ITERATIONS, coarse_fraction=mirror.MIRROR_COARSE_FRACTION,
                                            axis_search_at=mirror.MIRROR_AXIS_SEARCH_AT), objective=objective, rig=rig)
    judge = selection_judge(make_renderer(volume, engine, "cpu"), result.vessel_selection)
    return judge, result.poses


def main() -> None:
    models = load_models(runtime="torch")
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):
        axis = 2 - int(np.argmax(np.abs(case.cta.ijk_to_ras[0, :3]) / np.asarray(case.cta.spacing_mm)))
        flip = lambda volume: volume.like(np.ascontiguousarray(np.flip(volume.array, axis)))  # noqa: E731
        for name, cta, vessels in (("correct", case.cta, case.vessels), ("mirrored", flip(case.cta), flip(case.vessels))):
            t0 = time.perf_counter()
            reg = register_case(cta, case.runs, models=models, segmentation=oracle_vessels(cta, vessels))
            r = reg.registration
            if r.mirror is None:
                continue
            objective = reg.options.objective
            rig = nominal_poses(case.runs)
            estimate = patient_pose(reg.views["pa"].search_pose, rig["pa"])
            views = {k: reg.views[k].prepared for k in ("pa", "lat")}
            renderer = reg.renderer
            factors = mirror.work_factors(renderer.volume)
            work, shift = renderer.volume.coarsened(factors)
            selection = r.vessel_selection
            judge = make_renderer(work if selection is None or not selection.applied else
                                  work.with_vessels(np.argwhere(coarse_mask(selection.keep, factors))), renderer.engine, "cpu")
            tournament = Tournament(r.tto_runs, r.tto_objective, r.chosen_start, r.vessel_selection)
            result_poses = {k: shift @ T for k, T in tournament.result.poses.items()}
            row = {"case": case.name, "cta": name, "margin": r.mirror.margin, "register_s": time.perf_counter() - t0}
            row["result"] = terms(judge, result_poses, views, objective)
            plane = mirror.midsagittal_plane(work.cta)
            mj, mp = short_tto(mirror.mirrored_volume(work, plane), views, estimate, shift, rig, objective, renderer.engine)
            row["mirrored"] = terms(mj, mp, views, objective)
            gj, gp = short_tto(work, views, estimate, shift, rig, objective, renderer.engine)
            row["given_short"] = terms(gj, gp, views, objective)
            print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
