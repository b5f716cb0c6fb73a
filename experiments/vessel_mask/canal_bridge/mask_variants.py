"""The CTA vessel mask with module constants of ``geopose.cta.masks`` set otherwise, scored per vessel group against
phantom truth (``benchmarks/bench_vessels.py``'s ``score``); one subject per seed, every variant on it. One JSON line per
seed and variant.

    .venv/bin/python experiments/vessel_mask/canal_bridge/mask_variants.py 6020-6039 \\
        '{"base": {}, "mouth4": {"CANAL_MOUTH_MM": 4.0}}' rows.jsonl
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))
from bench_vessels import write_scored  # noqa: E402

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.cta import masks as M  # noqa: E402
from geopose.cta import vessel_mask_from_cta  # noqa: E402
from geopose.phantom import make_subject  # noqa: E402


def main() -> None:
    seeds, variants, path = seed_range(sys.argv[1]), json.loads(sys.argv[2]), Path(sys.argv[3])
    defaults = {name: getattr(M, name) for consts in variants.values() for name in consts}
    with path.open("w") as out:
        for seed in seeds:
            subject = make_subject(seed, spacing_mm=1.0)
            for variant, consts in variants.items():
                for name, value in {**defaults, **consts}.items():
                    setattr(M, name, value)
                t0 = time.perf_counter()
                mask = np.asarray(vessel_mask_from_cta(subject.cta).array) > 0
                write_scored(out, {"seed": seed, "variant": variant, "seconds": round(time.perf_counter() - t0, 2)},
                             mask, subject)


if __name__ == "__main__":
    main()
