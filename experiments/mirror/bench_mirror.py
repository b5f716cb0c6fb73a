"""Which statistic tells a left-right mirrored CTA from a correct one on the default path (the masks
computed from the CTA, no segmentation given)? Each held-out phantom is registered as it is and with
its CTA mirrored (the array flipped along the left-right axis, the header kept: what a CTA whose
header swaps the sides gives); then, at each registration's own result, the candidate tests:

* ``all``: today's ``mirror.mirror_test`` (the CTA against its mirror image, every computed vessel);
* ``reread``: the same short TTO (12 steps, the opacified vessels read after the coarse steps, as the
  tournament does) from the result's patient pose for the CTA and for its mirror image, each judged
  by the objective on the vessels it read;
* ``selection``: the tournament's opacified vessels mirrored with the CTA (not re-read).

    .venv/bin/python experiments/mirror/bench_mirror.py --seeds 6010-6019 --doc experiments/mirror/mirror_table.md
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import parse_heldout_args  # noqa: E402

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import Objective, TTOSchedule  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.biplane import view_poses  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.mirror import MIRROR_TTO_ITERATIONS, mirror_test, mirrored_volume  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.register.tournament import optimise_from_starts  # noqa: E402
from geopose.register.tto import tto_views  # noqa: E402
from geopose.render.renderer import TorchRenderer, make_renderer  # noqa: E402

SHORT = TTOSchedule(MIRROR_TTO_ITERATIONS)


def midplane_mirrored(volume):
    """``volume`` mirrored across the plane through its cranium mask's centroid normal to the left-right
    axis (the grid's centre plane, then a whole-voxel shift; air and empty masks fill in)."""
    from geopose.render.volume import RenderVolume
    cta = volume.cta
    axis = 2 - int(np.argmax(np.abs(cta.ijk_to_ras[0, :3]) / np.asarray(cta.spacing_mm)))
    cranium = volume.mask("cranium")
    n = cta.array.shape[axis]
    shift = int(round(2 * np.nonzero(cranium)[axis].mean() - (n - 1)))

    def flip(a, fill):
        f = np.flip(a, axis)
        out = np.full_like(f, fill)
        src = [slice(None)] * 3
        dst = [slice(None)] * 3
        src[axis] = slice(max(0, -shift), n - max(0, shift))
        dst[axis] = slice(max(0, shift), n - max(0, -shift))
        out[tuple(dst)] = f[tuple(src)]
        return out

    out = cta.like(flip(cta.array, cta.array.min()))
    masks = {name: out.like(flip(volume.mask(name), 0).astype(np.uint8)) for name in ("cranium", "vessels")
             if volume.mask(name) is not None}
    return RenderVolume(out, masks, finest_spacing_mm=volume.finest_spacing_mm)


def short_tto(volume, views, X, rig, reread: bool, iterations: int = MIRROR_TTO_ITERATIONS):
    """The objective (both views) after the short TTO from patient pose ``X`` on ``volume`` and the
    per-view terms; with ``reread`` the opacified vessels are read after the coarse steps and judge the result."""
    from geopose.register.objective import objective_value
    objective = Objective() if reread else Objective(read_opacified=False)
    run = optimise_from_starts(TorchRenderer(volume, "cpu"), tto_views(views, view_poses(X, rig)), {"x": X}, rig,
                               TTOSchedule(iterations), objective=objective)["x"]
    judged = run.vessel_selection.volume if run.vessel_selection is not None and run.vessel_selection.applied else volume
    judge = make_renderer(judged, "torch", "cpu")
    terms = {k: objective_value(judge, run.poses[k], views[k], objective) for k in views}
    return sum(t.loss for t in terms.values()), {k: (t.mncc, t.dice_loss, t.vessel_ncc) for k, t in terms.items()}


def short_tto_objective(volume, views, X, rig, reread: bool) -> float:
    return short_tto(volume, views, X, rig, reread)[0]


def measure(reg, case) -> dict:
    rig, X = reg.registration.rig, reg.registration.patient_pose
    views = {k: v.prepared for k, v in reg.views.items()}
    volume = reg.renderer.volume
    out = {"mpcd_mm": [carotid_mpcd(reg.views[k].final_pose, case.true_poses[k], case.runs[k].detector,
                                    case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm for k in ("pa", "lat")],
           "quality": [reg.views[k].quality.flag for k in ("pa", "lat")]}
    t = time.perf_counter()
    out["all"] = mirror_test(reg.renderer, views, X, rig).margin
    t, out["t_all"] = time.perf_counter(), time.perf_counter() - t
    same = short_tto_objective(volume, views, X, rig, True)
    flipped = short_tto_objective(mirrored_volume(volume), views, X, rig, True)
    out["reread"], out["reread_losses"] = flipped - same, (same, flipped)
    t, out["t_reread"] = time.perf_counter(), time.perf_counter() - t
    for name, iterations in (("mid12", 12), ("mid24", 24)):
        same, same_terms = short_tto(volume, views, X, rig, True, iterations)
        flipped, flipped_terms = short_tto(midplane_mirrored(volume), views, X, rig, True, iterations)
        out[name], out[name + "_terms"] = flipped - same, (same_terms, flipped_terms)
    selection = reg.registration.vessel_selection
    if selection is not None and selection.applied:
        own = pair_objective(make_renderer(selection.volume, "torch", "cpu"), view_poses(X, rig), views, Objective())
        out["selection"] = short_tto_objective(mirrored_volume(selection.volume), views, X, rig, False) - own
    return out


def main() -> None:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "6010-6019")
    models = load_models(runtime="torch")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            case = phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm)
            axis = 2 - int(np.argmax(np.abs(case.cta.ijk_to_ras[0, :3]) / np.asarray(case.cta.spacing_mm)))
            for name, cta in (("correct", case.cta), ("mirrored", case.cta.like(np.ascontiguousarray(np.flip(case.cta.array, axis))))):
                t0 = time.perf_counter()
                reg = register_case(cta, case.runs, models=models)
                row = {"seed": seed, "cta": name, "t_register": time.perf_counter() - t0} | measure(reg, case)
                rows.append(row)
                print(json.dumps(row, default=float), file=sys.stderr, flush=True)
    lines = ["| seed | CTA | mPCD PA / LAT (mm) | flags | all | reread | selection | mid12 | mid24 |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['cta']} | {r['mpcd_mm'][0]:.1f} / {r['mpcd_mm'][1]:.1f} | {' / '.join(r['quality'])} | "
                     f"{r['all']:+.3f} | {r['reread']:+.3f} | {r.get('selection', float('nan')):+.3f} | {r['mid12']:+.3f} | {r['mid24']:+.3f} |")
    text = "\n".join(lines)
    print(text)
    if args.doc:
        args.doc.write_text(text + "\n")
        args.doc.with_suffix(".json").write_text(json.dumps(rows, default=float, indent=1))


if __name__ == "__main__":
    main()
