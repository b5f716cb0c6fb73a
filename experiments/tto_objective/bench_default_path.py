"""The default path per held-out phantom, with what the TTO did: each case registered as a user does
(`register_case`, CTA and the two runs, masks computed), scored with the phantom's truth. Per seed: the final
carotid mPCD (mm, PA / LAT) and rotation error (deg), the quality flags, each TTO start's result (mPCD, objective),
the start kept (or the networks' estimate, when the trust rule kept it) and where the opacified vessels were read
(start, iteration, share of the computed mask's voxels kept).

    .venv/bin/python experiments/tto_objective/bench_default_path.py --seeds 6010-6029 --doc experiments/tto_objective/default_path_table.md
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import parse_heldout_args, publish  # noqa: E402

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.metrics.measures import pose_errors  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402

VIEWS = ("pa", "lat")


def case_row(seed: int, spacing_mm: float, models) -> dict:
    case = phantom_case(seed, Path(tempfile.mkdtemp()), spacing_mm)
    reg = register_case(case.cta, case.runs, models=models)

    def mpcd(poses) -> list[float]:
        return [round(float(carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                                         case.carotid_points_mm)[0].detector_mm), 2) for k in VIEWS]

    r = reg.registration
    selection = r.vessel_selection
    return {
        "seed": seed, "final_mm": mpcd({k: reg.views[k].final_pose for k in VIEWS}),
        "estimate_mm": mpcd({k: reg.views[k].search_pose for k in VIEWS}),
        "rotation_deg": round(float(pose_errors(reg.views["pa"].final_pose[None], case.true_poses["pa"][None]).rotation_deg[0]), 2),
        "flags": [reg.views[k].quality.flag for k in VIEWS], "chosen": r.chosen_start, "kept_estimate": bool(r.kept_learned),
        "runs": {name: {"mm": mpcd(run.poses), "objective": round(float(r.tto_objective[name]), 3)}
                 for name, run in r.tto_runs.items() if name in r.tto_objective},
        "read": None if selection is None else {"start": selection.start, "iteration": selection.iteration,
                                                "kept": round(selection.kept_fraction, 3)},
        "seconds": round(float(reg.runtimes_s["total"]), 1),
    }


def main() -> None:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "6010-6029")
    models = load_models(runtime="torch")
    rows = []
    for seed in seeds:
        rows.append(case_row(seed, args.spacing_mm, models))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    lines = [f"`{' '.join(sys.argv)}`", "", "| seed | final mPCD PA / LAT (mm) | rot. (deg) | flags | networks' estimate (mm) | "
             "TTO runs: mPCD (mm), objective | kept | opacified vessels read at |", "|---|---|---:|---|---|---|---|---|"]
    for r in rows:
        runs = "; ".join(f"{name}: {v['mm'][0]:.2f} / {v['mm'][1]:.2f}, {v['objective']:.3f}" for name, v in r["runs"].items())
        kept = "networks' estimate" if r["kept_estimate"] else r["chosen"]
        read = "-" if r["read"] is None else f"{r['read']['start']}, it. {r['read']['iteration']}, {100 * r['read']['kept']:.0f} %"
        lines.append(f"| {r['seed']} | {r['final_mm'][0]:.2f} / {r['final_mm'][1]:.2f} | {r['rotation_deg']:.2f} | "
                     f"{', '.join(r['flags'])} | {r['estimate_mm'][0]:.2f} / {r['estimate_mm'][1]:.2f} | {runs} | {kept} | {read} |")
    final = np.array([r["final_mm"] for r in rows]).ravel()
    rot = np.array([r["rotation_deg"] for r in rows])
    ok = [f == "ok" for r in rows for f in r["flags"]]
    lines += ["", "| views | mean mPCD (mm) | median | < 2 mm | < 5 mm | mean rot. (deg) | median rot. | < 2 mm and ok | > 5 mm and ok | "
              "mean s |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
              f"| {final.size} | {final.mean():.2f} | {np.median(final):.2f} | {(final < 2).sum()} | {(final < 5).sum()} | "
              f"{rot.mean():.2f} | {np.median(rot):.2f} | {sum(o and e < 2 for o, e in zip(ok, final))} / {(final < 2).sum()} | "
              f"{sum(o and e > 5 for o, e in zip(ok, final))} / {(final > 5).sum()} | {np.mean([r['seconds'] for r in rows]):.1f} |"]
    publish("\n".join(lines), args.doc, "The default path per held-out phantom",
            "Each case registered as a user does (CTA and two runs, masks computed); scored with the phantom's truth. "
            "See opacified_read.md.")


if __name__ == "__main__":
    main()
