"""The pairing test on mirrored CTAs: validation phantoms registered with their CTA's array flipped left-right, the
header kept (as ``geopose bench --mirrored-subjects`` does), on the user's path (``register_case``, masks computed).
One JSON row per seed: the pairing test, the mirror test's margins, the flags and reasons.

    python mirrored_gain.py PHANTOM_DIR ROWS.jsonl SEED [SEED ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from geopose.bench.cases import flipped_left_right
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.register.pipeline import register_case


def main(argv: list[str]) -> None:
    phantoms, rows_path, seeds = Path(argv[0]), Path(argv[1]), [int(s) for s in argv[2:]]
    for seed in seeds:
        folder = phantoms / str(seed)
        runs = {k: read_dsa(folder / f"dsa_{k}.dcm") for k in ("pa", "lat")}
        reg = register_case(flipped_left_right(load_cta(folder / "cta.nii.gz")), runs)
        pairing, mirror = reg.registration.pairing, reg.registration.mirror
        row = {"seed": seed, "pairing": None if pairing is None else pairing.as_dict(),
               "mirror": None if mirror is None else mirror.as_dict(),
               "quality": {k: v.quality.flag for k, v in reg.views.items()},
               "reasons": {k: list(v.quality.reasons) for k, v in reg.views.items()}}
        with rows_path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(seed, None if pairing is None else round(pairing.gain, 3), None if mirror is None else round(mirror.margin, 3),
              row["quality"], flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
