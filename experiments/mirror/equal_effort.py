"""Does the mirror test's margin lean towards the CTA as given because the two sides get unequal effort?

The result has had the whole registration (Init, Refine, search, the TTO tournament); its mirror image only the test's
12 steps from the networks' estimate. Inside each registration this script also runs the CTA as given through those
same 12 steps from the same start, judged the same way (``mirror.short_fit_loss``): ``short_loss``. The rows were
made before the product kept the rule (their flags are the session-56 rule's); run now, the numbers are the same and
the flags follow the kept rule. Each phantom folder (as ``geopose phantom`` writes it) is registered as written and mirrored
(``register_case``, the CTA and the two runs only). One JSON line per registration: the three objectives (both views
summed), the carotid mPCD per view, the flags.

    .venv/bin/python experiments/mirror/equal_effort.py /tmp/ph1 6010 6049 > equal_effort_1mm.jsonl
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from heldout import view_errors, written_correct_and_mirrored  # noqa: E402  (also puts the library on the path, geopose before torch)

import torch  # noqa: E402
from types import SimpleNamespace  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import pipeline  # noqa: E402
from geopose.register.evaluate import load_truth  # noqa: E402
from geopose.register.mirror import short_fit_loss, work_factors  # noqa: E402

SHORT: dict[str, float] = {}
_product = pipeline.mirror_test


def with_equal_effort(renderer, views, tournament, estimate, rig, objective, device, *args, **kwargs):
    """The product's test; beside it, the CTA as given through the hypothesis's own short fit."""
    test = _product(renderer, views, tournament, estimate, rig, objective, device, *args, **kwargs)
    work, shift = renderer.volume.coarsened(work_factors(renderer.volume))
    SHORT["short_loss"] = short_fit_loss(work, renderer.engine, views, shift @ estimate, rig, objective, device)
    return test


def main() -> None:
    pipeline.mirror_test = with_equal_effort
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    folders = Path(sys.argv[1])
    for seed, name, cta, runs in written_correct_and_mirrored(folders, int(sys.argv[2]), int(sys.argv[3])):
        truth = load_truth(folders / str(seed) / "cta.nii.gz")
        scored = SimpleNamespace(true_poses=truth.poses, runs=runs, carotid_points_mm=truth.carotid_points_mm)
        SHORT.clear()
        reg = pipeline.register_case(cta, runs, models=models)
        m = reg.registration.mirror
        row = {"seed": seed, "cta": name, "loss": round(m.loss, 4), "mirrored_loss": round(m.mirrored_loss, 4),
               "short_loss": round(SHORT["short_loss"], 4), "margin": round(m.margin, 4),
               "final": view_errors(scored, {k: reg.views[k].final_pose for k in runs}),
               "flags": [reg.views[k].quality.flag for k in ("pa", "lat")]}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
