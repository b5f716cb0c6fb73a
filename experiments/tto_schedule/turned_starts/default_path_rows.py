"""The loop the pipeline variants share: each validation phantom registered as a user does (``register_case`` with
the CTA and the two runs, masks computed), one JSON line per seed: the start chosen, the TTO's objectives, the final
carotid mPCD (mm) and rotation error (deg) per view, the flags and the time (s), with the variant's own ``info``."""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from heldout import view_errors  # noqa: E402

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402


def run_seeds(seeds: list[int], out_path: str, mode: str, info: dict) -> None:
    """Register each seed (2 mm phantoms, default options) and append its row to ``out_path``; ``info`` is filled by
    the variant's patch during the registration and cleared before each."""
    models = load_models(runtime="torch")
    with open(out_path, "a") as out:
        for seed in seeds:
            info.clear()
            with tempfile.TemporaryDirectory() as tmp:
                case = phantom_case(seed, Path(tmp), 2.0)
                reg = register_case(case.cta, case.runs, models=models)
            r = reg.registration
            row = {"seed": seed, "mode": mode, "kept_learned": bool(r.kept_learned), "chosen": r.chosen_start,
                   "tto_objective": r.tto_objective,
                   "final": view_errors(case, {k: reg.views[k].final_pose for k in ("pa", "lat")}),
                   "flags": {k: reg.views[k].quality.flag for k in ("pa", "lat")},
                   "total_s": round(reg.runtimes_s["total"], 2), "tto_s": round(reg.runtimes_s.get("tto", 0), 2), **info}
            print(json.dumps(row), file=out, flush=True)
