"""How the artery classifier's cut changes the CTA vessel mask: a plain threshold on its probability, or hysteresis
(keep the tree's components of p >= low that hold a voxel of p >= high), scored per vessel group against phantom
truth with ``benchmarks/bench_vessels.py``'s ``score``.

    .venv/bin/python experiments/vessel_mask/artery_threshold/threshold.py --seeds 6010-6019 --json rows.jsonl
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))
from bench_vessels import write_scored  # noqa: E402

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.cta.arteries import artery_features, load_artery_classifier  # noqa: E402
from geopose.cta.masks import _back_to_full, cranium_mask_from_cta, vessel_candidates  # noqa: E402
from geopose.phantom import make_subject  # noqa: E402

VARIANTS = {"p>=0.5": (0.5, None), "p>=0.4": (0.4, None), "p>=0.3": (0.3, None), "p>=0.2": (0.2, None),
            "hyst 0.5/0.3": (0.5, 0.3), "hyst 0.5/0.2": (0.5, 0.2), "hyst 0.5/0.1": (0.5, 0.1),
            "hyst 0.7/0.2": (0.7, 0.2)}


def cut(shape, idx: np.ndarray, p: np.ndarray, high: float, low: float | None) -> np.ndarray:
    """The kept voxels ([k, j, i] bool): p >= high, or (``low``) the 26-connected components of p >= low that hold one."""
    out = np.zeros(shape, bool)
    if low is None:
        out[tuple(idx[p >= high].T)] = True
        return out
    out[tuple(idx[p >= low].T)] = True
    comps = sitk.GetArrayFromImage(sitk.ConnectedComponent(sitk.GetImageFromArray(out.astype(np.uint8)), True))
    seeds = np.unique(comps[tuple(idx[p >= high].T)])
    return np.isin(comps, seeds[seeds > 0])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="6010-6019")
    ap.add_argument("--spacing", type=float, default=1.0)
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    classifier = load_artery_classifier()
    with open(args.json, "w") as f:
        for seed in seed_range(args.seeds):
            subject = make_subject(seed, spacing_mm=args.spacing)
            work, tree, _ = vessel_candidates(subject.cta)
            features, idx = artery_features(work, tree, np.asarray(cranium_mask_from_cta(work).array) > 0)
            p = classifier.probability(features)
            for name, (high, low) in VARIANTS.items():
                kept = cut(tree.shape, idx, p, high, low)
                mask = _back_to_full(work.like(kept.astype(np.uint8)), subject.cta) > 0
                write_scored(f, {"seed": seed, "variant": name}, mask, subject)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
