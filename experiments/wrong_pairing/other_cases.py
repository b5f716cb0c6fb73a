"""The pairing test on correct pairings outside the plain phantoms: densely opacified runs and real head CTs with a
phantom's arteries (validation seeds), registered as ``geopose bench`` registers its cases (``register_case``, masks
computed). One JSON row per case: the gain per view and its mean, the flags and reasons.

    python other_cases.py ROWS.jsonl HEADSQ_MHD
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from geopose.bench.cases import headsq_case, phantom_case
from geopose.register.pipeline import register_case

DENSE = ("all_territories", "avm", "late_venous")


def cases(headsq: str):
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (6010, 6011, 6012):
            for injection in DENSE:
                yield lambda seed=seed, injection=injection: phantom_case(seed, Path(tmp) / f"{seed}-{injection}", 1.0, injection)
        for seed in (3, 4, 5):  # the benchmark runs headsq seeds 0..; these are others
            yield lambda seed=seed: headsq_case(headsq, seed, arteries=True)


def main(argv: list[str]) -> None:
    rows_path, headsq = Path(argv[0]), argv[1]
    for make in cases(headsq):
        case = make()
        reg = register_case(case.cta, case.runs)
        pairing = reg.registration.pairing
        row = {"case": case.name, "pairing": None if pairing is None else pairing.as_dict(),
               "quality": {k: v.quality.flag for k, v in reg.views.items()},
               "reasons": {k: list(v.quality.reasons) for k, v in reg.views.items()}}
        with rows_path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(case.name, None if pairing is None else round(pairing.gain, 3), row["quality"], flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
