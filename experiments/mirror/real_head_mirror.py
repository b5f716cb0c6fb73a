"""The mirror test on the real head CT headsq made a CTA with a phantom's arteries (``bench.cases.headsq_case``), as
given and mirrored left-right (``bench.run.evaluate_mirrored``), for the seeds given: one line per registration with
the mirror record's numbers and the flags.

    .venv/bin/python experiments/mirror/real_head_mirror.py ../shared/data/headsq/quarter_sidecar.mhd 0 1
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import heldout  # noqa: E402,F401  (puts the library on the path, geopose before torch)

import torch  # noqa: E402

from geopose.bench.cases import headsq_case  # noqa: E402
from geopose.bench.run import BenchSettings, evaluate_mirrored  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register.pipeline import register_case  # noqa: E402


def numbers(record: dict | None) -> dict | None:
    return None if record is None else {k: round(v, 3) if isinstance(v, float) else v for k, v in record.items()
                                        if k != "plane"}


def main() -> None:
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    for seed in (int(s) for s in sys.argv[2:]):
        case = headsq_case(sys.argv[1], seed, arteries=True)
        given = register_case(case.cta, case.runs, models=models)
        mirror = given.registration.mirror
        print(case.name, "correct", numbers(None if mirror is None else mirror.as_dict()),
              {k: given.views[k].quality.flag for k in ("pa", "lat")}, flush=True)
        mirrored = evaluate_mirrored(case, models, BenchSettings())
        print(case.name, "mirrored", numbers(mirrored["mirror"]), mirrored["quality"], flush=True)


if __name__ == "__main__":
    main()
