"""Should the vessel term compare a compressed DRR of the vessel channel, so that thick vessels pull less?

A vessel's projection grows with the chord through it: a jugular vein or a dural sinus of the computed mask draws 2-4x
brighter than an intracranial artery, and the vessel term's NCC weighs each pixel by its brightness. ``--mode``
compresses the rendered vessel channel (over its own maximum, x) before the NCC, in both engines' kernels, for this
process only: ``sqrt`` (sqrt(x + 1e-4) - 0.01) or ``clipNN`` (x clipped at the NNth percentile of its positive pixels);
``linear`` is today's. ``--protocol drift``: the default TTO started at the true pose, masks computed (the benchmark's
drift row, ``experiments/vessel_mask/selection_oracle.py``'s protocol); ``--protocol default``: ``register_case`` with
the CTA and the two runs (the user's path), one JSON line per phantom.

    .venv/bin/python experiments/vessel_weight/compressed.py --protocol drift --mode sqrt clip90 --seeds 6020-6031
    .venv/bin/python experiments/vessel_weight/compressed.py --protocol default --mode sqrt --seeds 6010-6034
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "vessel_mask"))


def _take(flag: str) -> list[str]:
    """The values after ``flag`` up to the next option, removed from the command line (before the shared parser)."""
    i = sys.argv.index(flag)
    j = next((n for n in range(i + 1, len(sys.argv)) if sys.argv[n].startswith("--")), len(sys.argv))
    values = sys.argv[i + 1:j]
    del sys.argv[i:j]
    return values


MODES = _take("--mode")
PROTOCOL = _take("--protocol")[0]

from heldout import heldout_phantoms, view_errors  # noqa: E402
from selection_oracle import DROPPED, drift_rows  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import objective  # noqa: E402
from geopose.register import register_case  # noqa: E402

MODE = {"now": "linear"}


def compress(v):
    """The rendered vessel channel ``(H, W)`` (numpy or torch) compressed by ``MODE["now"]``."""
    mode = MODE["now"]
    top = float(v.detach().max()) if hasattr(v, "detach") else float(np.max(v))
    if mode == "linear" or top <= 0:
        return v
    x = v / top
    if mode == "sqrt":
        return (x + 1e-4) ** 0.5 - 0.01
    values = x.detach().numpy() if hasattr(x, "detach") else x
    c = float(np.quantile(values[values > 0], float(mode[4:]) / 100))
    return x.clamp(max=c) if hasattr(x, "clamp") else np.minimum(x, c)


for kernels in (objective._TorchKernels, objective._NumpyKernels):
    kernels.ncc = staticmethod(lambda a, b, _ncc=kernels.ncc: _ncc(a, compress(b)))


def main() -> None:
    if PROTOCOL == "drift":
        def setter(mode):
            def setup(read) -> None:
                read.drop, MODE["now"] = DROPPED["computed"], mode
            return setup
        drift_rows({mode: setter(mode) for mode in MODES}, __doc__.splitlines()[0], "6020-6031")
        return
    models = load_models(runtime="torch")
    for args, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6034"):
        row = {"case": case.name}
        for mode in MODES:
            MODE["now"] = mode
            reg = register_case(case.cta, case.runs, models=models)
            r = reg.registration
            row[mode] = {"final": view_errors(case, {k: reg.views[k].final_pose for k in ("pa", "lat")}),
                         "chosen": r.chosen_start, "kept_learned": bool(r.kept_learned),
                         "mirror_margin": None if r.mirror is None else round(float(r.mirror.margin), 4),
                         "flags": [reg.views[k].quality.flag for k in ("pa", "lat")]}
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
