"""The pairing test on a given segmentation (session 60): validation phantoms 6010-6029 at 1 mm registered by
``register_case`` with the CTA, two runs and ``segmentation=`` either the phantom's arteries (a clean artery
segmentation) or the mask computed without the artery classifier (``thresholded``: veins and bone rims in it, as a
thresholded Segment Editor segmentation may have), with its own runs (right) or the next subject's (crossed; 6029's
with 6010's). One JSON row per pair: the pairing test, flags and reasons.

    python given_segmentation.py PHANTOM_DIR ROWS.jsonl right|crossed arteries|thresholded SEED [SEED ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from geopose.cta import load_cta
from geopose.cta.masks import vessel_mask_from_cta
from geopose.dsa import read_dsa
from geopose.phantom import labels as L
from geopose.register.pipeline import register_case


def main(argv: list[str]) -> None:
    phantoms, out, variant, seg_kind = Path(argv[0]), Path(argv[1]), argv[2], argv[3]
    for seed in [int(s) for s in argv[4:]]:
        folder = phantoms / str(seed)
        cta = load_cta(folder / "cta.nii.gz")
        if seg_kind == "arteries":
            labels = load_cta(folder / "labels.nii.gz", check_hu=False)
            seg = labels.like(L.vessel_mask(labels.array).astype(np.uint8))
        else:
            seg = vessel_mask_from_cta(cta, arteries_only=False)
        runs_of = folder if variant == "right" else folder.parent / str(seed + 1 if seed not in (6029, 6049) else seed - 19)
        runs = {k: read_dsa(runs_of / f"dsa_{k}.dcm") for k in ("pa", "lat")}
        reg = register_case(cta, runs, segmentation=seg)
        r = reg.registration
        row = {"seed": seed, "runs": int(runs_of.name), "variant": variant, "segmentation": seg_kind,
               "pairing": r.pairing.as_dict() if r.pairing else None,
               "flags": {k: v.quality.flag for k, v in reg.views.items()},
               "reasons": {k: list(v.quality.reasons) for k, v in reg.views.items()}}
        with out.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(seed, variant, seg_kind, row["flags"], flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
