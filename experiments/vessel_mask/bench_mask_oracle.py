"""How far does the computed CTA vessel mask hold the default path back? Each held-out phantom is registered
as a user does (`register_case`, the cranium mask computed) with four vessel masks handed in:

* ``computed``: none given (the mask computed from the CTA: the default path);
* ``no veins``: the computed mask less the phantom's venous sinuses and jugular veins (an oracle);
* ``arteries only``: the computed mask within the phantom's arteries (precision 100 %, an oracle);
* ``true arteries``: the phantom's arteries (the benchmark's upper-bound input).

    .venv/bin/python experiments/vessel_mask/bench_mask_oracle.py --seeds 6010-6019 --doc experiments/vessel_mask/mask_oracle_table.md
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
from geopose.cta import load_cta, vessel_mask_from_cta  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402

MASKS = ("computed", "no veins", "arteries only", "true arteries")


def case_rows(seed: int, spacing_mm: float, models) -> list[dict]:
    folder = Path(tempfile.mkdtemp())
    case = phantom_case(seed, folder, spacing_mm)
    labels = load_cta(folder / "labels.nii.gz", check_hu=False).array
    computed = vessel_mask_from_cta(case.cta).array > 0
    arteries = L.vessel_mask(labels)
    veins = np.isin(labels, L.with_intracranial([L.VENOUS_SINUS]))
    masks = {"computed": None, "no veins": computed & ~veins, "arteries only": computed & arteries, "true arteries": arteries}
    rows = []
    for name, mask in masks.items():
        segmentation = None if mask is None else case.cta.like(mask.astype(np.uint8))
        reg = register_case(case.cta, case.runs, models=models, segmentation=segmentation)
        mpcd = [carotid_mpcd(reg.views[k].final_pose, case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                             case.carotid_points_mm)[0].detector_mm for k in ("pa", "lat")]
        rows.append({"seed": seed, "mask": name, "mpcd_mm": [round(float(m), 2) for m in mpcd],
                     "flags": [reg.views[k].quality.flag for k in ("pa", "lat")]})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "6010-6019")
    models = load_models(runtime="torch")
    rows = [row for seed in seeds for row in case_rows(seed, args.spacing_mm, models)]
    lines = [f"`{' '.join(sys.argv)}`", "", "Carotid mPCD (mm) of the final poses, PA / LAT, and the quality flags:", "",
             "| seed | " + " | ".join(MASKS) + " |", "|---|" + "---|" * len(MASKS)]
    for seed in seeds:
        by = {r["mask"]: r for r in rows if r["seed"] == seed}
        lines.append(f"| {seed} | " + " | ".join(f"{by[m]['mpcd_mm'][0]:.2f} / {by[m]['mpcd_mm'][1]:.2f} ({by[m]['flags'][0]}, "
                                                  f"{by[m]['flags'][1]})" for m in MASKS) + " |")
    lines += ["", "| vessel mask | mean | median | views < 2 mm | views < 5 mm |", "|---|---:|---:|---:|---:|"]
    for m in MASKS:
        v = np.array([x for r in rows if r["mask"] == m for x in r["mpcd_mm"]])
        lines.append(f"| {m} | {v.mean():.2f} | {np.median(v):.2f} | {(v < 2).sum()} / {v.size} | {(v < 5).sum()} / {v.size} |")
    publish("\n".join(lines), args.doc, "The default path with oracle vessel masks", "Held-out phantoms, 2 mm; see vessel_segmentation.md.")


if __name__ == "__main__":
    main()
