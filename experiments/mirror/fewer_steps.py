"""Can the mirror test's two short fits (the mirrored hypothesis and the CTA as given, equal effort) run fewer TTO
steps than 12 and decide the same? Each phantom folder (as ``geopose phantom`` writes it) is registered as written and
mirrored (``register_case``, the CTA and the two runs only) with ``mirror.MIRROR_TTO_ITERATIONS`` set to the steps
given. One JSON line per registration: the mirror record's numbers (no plane) and the mirror stage's time (s).

    .venv/bin/python experiments/mirror/fewer_steps.py /tmp/ph1 6010 6049 8 > fewer_steps_8.jsonl
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from heldout import written_correct_and_mirrored  # noqa: E402  (also puts the library on the path, geopose before torch)

import torch  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import mirror, pipeline  # noqa: E402


def main() -> None:
    mirror.MIRROR_TTO_ITERATIONS = int(sys.argv[4])
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    for seed, name, cta, runs in written_correct_and_mirrored(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])):
        reg = pipeline.register_case(cta, runs, models=models)
        record = reg.registration.mirror.as_dict()
        record.pop("plane")
        print(json.dumps({"seed": seed, "cta": name, **{k: round(v, 4) if isinstance(v, float) else v
                                                          for k, v in record.items()},
                          "mirror_s": round(reg.runtimes_s["mirror"], 2)}), flush=True)


if __name__ == "__main__":
    main()
