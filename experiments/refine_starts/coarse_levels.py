"""Greedy Refine and the similarity search on coarser CTA levels: per held-out phantom, the default registration
(``register_case`` with the CTA and the two runs) with ``estimate_voxel_per_pixel`` at the renderers' own 1.5 and at
3; each one's final and estimated carotid mPCD per view, flags and stage times (issue 33: the result before the TTO).

    .venv/bin/python experiments/refine_starts/coarse_levels.py --seeds 6010-6029 --doc /tmp/coarse.jsonl
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402

#: Rows: the name and the level setting of greedy Refine and the search.
SETTINGS = (("default", 1.5), ("coarse", 3.0))


def main() -> None:
    models = load_models(runtime="torch")
    for _, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):

        def mpcd(poses: dict) -> list[float]:
            return [round(carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                                       case.carotid_points_mm)[0].detector_mm, 3) for k in ("pa", "lat")]

        row = {"seed": int(case.name.split("-")[-1])}
        for name, voxel_per_pixel in SETTINGS:
            reg = register_case(case.cta, case.runs, models=models,
                                options=RegistrationOptions(estimate_voxel_per_pixel=voxel_per_pixel))
            row[name] = {"final": mpcd({k: v.final_pose for k, v in reg.views.items()}),
                         "estimate": mpcd({k: v.search_pose for k, v in reg.views.items()}),
                         "flags": [reg.views[k].quality.flag for k in ("pa", "lat")],
                         "t": {k: round(v, 2) for k, v in reg.runtimes_s.items()}}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
