"""Should the mirror test's hypothesis run start at the tournament's result rather than the networks' estimate?

On 1 mm CTAs two mirrored validation phantoms pass the test at +0.063 because the hypothesis run (12 half-size steps)
does not arrive from an estimate 10-15 mm off (``experiments/resolution/resolution.md``). Each phantom folder (as
``geopose phantom`` writes it) is registered as written and mirrored (``register_case``, CTA and runs only); inside
it the mirror test runs twice: as the product does (from the networks' estimate) and from the tournament's result
(its patient pose). The product's decision is not changed. One JSON line per registration: both margins.

    .venv/bin/python experiments/mirror/result_start.py /tmp/ph1 6010 6029 > rows.jsonl
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from heldout import written_correct_and_mirrored  # noqa: E402  (also puts the library on the path, geopose before torch)

import torch  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import pipeline  # noqa: E402
from geopose.register.biplane import patient_pose  # noqa: E402

MARGINS: dict[str, float] = {}
_product = pipeline.mirror_test


def both_starts(renderer, views, tournament, estimate, rig, *args, **kwargs):
    """The product's test, and the same from the tournament's result; the product's is returned."""
    test = _product(renderer, views, tournament, estimate, rig, *args, **kwargs)
    X_result = patient_pose(tournament.result.poses["pa"], rig["pa"])
    MARGINS["estimate"], MARGINS["result"] = test.margin, _product(renderer, views, tournament, X_result, rig, *args, **kwargs).margin
    return test


def main() -> None:
    pipeline.mirror_test = both_starts
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    for seed, name, cta, runs in written_correct_and_mirrored(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])):
        MARGINS.clear()
        pipeline.register_case(cta, runs, models=models)
        print(json.dumps({"seed": seed, "cta": name, **{k: round(v, 4) for k, v in MARGINS.items()}}), flush=True)


if __name__ == "__main__":
    main()
