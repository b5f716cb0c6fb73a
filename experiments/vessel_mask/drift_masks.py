"""Which mask makes the TTO drift from the truth on the default path? Each held-out phantom's default TTO is started
at the true pose (as the benchmark's drift row) with the CTA's masks as ``register_case`` makes them, or with one of
them replaced by an oracle from the phantom's labels, or with the vessel mask of a variant rule:

* ``computed``: both masks computed from the CTA (the user's path);
* ``true vessels`` / ``true cranium``: the phantom's arteries / cranium handed in, the other mask computed;
* ``computed, arteries only``: the computed vessel mask within the phantom's arteries (precision 100 %);
* ``computed + true arteries``: the computed vessel mask with every phantom artery added (recall 100 %);
* ``all lumen near bone``: lumen HU next to bone joined to the tree everywhere, not only in dark tubes;
* ``canal objectness 0.01``: the bony-canal rule's threshold lowered from 0.03.

Carotid mPCD (mm) of the TTO's end from the truth, with the vessel mask's voxel recall and precision against the
phantom's arteries.

    .venv/bin/python experiments/vessel_mask/drift_masks.py --seeds 6011-6019 --doc experiments/vessel_mask/drift_masks_table.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.cta import masks  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.engine import torch_renderer_for  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.tto import TTOSchedule, test_time_optimise, tto_views  # noqa: E402

VARIANTS = ("computed", "true vessels", "true cranium", "computed, arteries only", "computed + true arteries",
            "all lumen near bone", "canal objectness 0.01")


def variant_vessel_mask(cta, name: str) -> np.ndarray:
    """The computed vessel mask ([k, j, i] bool) under a variant rule (``masks`` patched for the call only)."""
    tubes, objectness = masks._dark_tubes, masks.CANAL_OBJECTNESS
    try:
        if name == "all lumen near bone":
            masks._dark_tubes = lambda a, spacing_mm: np.ones(a.shape, dtype=bool)
        if name == "canal objectness 0.01":
            masks.CANAL_OBJECTNESS = 0.01
        return masks.vessel_mask_from_cta(cta).array > 0
    finally:
        masks._dark_tubes, masks.CANAL_OBJECTNESS = tubes, objectness


def main() -> None:
    models = load_models(runtime="torch")
    options = RegistrationOptions().replace(**{"tto.iterations": 0})
    rows, out = [], sys.stdout
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6011-6019"):
        arteries = case.vessels.array > 0
        computed = variant_vessel_mask(case.cta, "computed")
        vessels = {"computed": None, "true vessels": arteries, "true cranium": None,
                   "computed, arteries only": computed & arteries, "computed + true arteries": computed | arteries,
                   "all lumen near bone": variant_vessel_mask(case.cta, "all lumen near bone"),
                   "canal objectness 0.01": variant_vessel_mask(case.cta, "canal objectness 0.01")}
        rig = nominal_poses(case.runs)
        X = patient_pose(case.true_poses["pa"], rig["pa"])
        row = {"case": case.name}
        for name in VARIANTS:
            mask = vessels[name]
            reg = register_case(case.cta, case.runs, models=models, options=options,
                                segmentation=None if mask is None else case.cta.like(mask.astype(np.uint8)),
                                cranium_mask=case.cranium if name == "true cranium" else None)
            prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
            result = test_time_optimise(torch_renderer_for(reg.renderer), tto_views(prepared, {k: X @ rig[k] for k in rig}),
                                        TTOSchedule(args.iterations), rig=rig)
            used = computed if mask is None else mask
            row[name] = {"drift_mm": [carotid_mpcd(result.poses[k], case.true_poses[k], case.runs[k].detector,
                                                   case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm
                                      for k in ("pa", "lat")],
                         "recall": float((used & arteries).sum() / arteries.sum()),
                         "precision": float((used & arteries).sum() / max(used.sum(), 1))}
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    lines = ["TTO from the truth, carotid mPCD PA / LAT (mm) of its end; vessel mask voxel recall / precision:", "",
             "| case | " + " | ".join(VARIANTS) + " |", "|---|" + "---|" * len(VARIANTS)]
    for row in rows:
        lines.append(f"| {row['case']} | " + " | ".join(
            f"{row[v]['drift_mm'][0]:.2f} / {row[v]['drift_mm'][1]:.2f} ({row[v]['recall']:.2f} / {row[v]['precision']:.2f})"
            for v in VARIANTS) + " |")
    lines.append("| mean | " + " | ".join(f"{np.mean([row[v]['drift_mm'] for row in rows]):.2f}" for v in VARIANTS) + " |")
    print("\n".join(lines), file=out, flush=True)


if __name__ == "__main__":
    main()
