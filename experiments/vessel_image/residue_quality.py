"""The DSA side alone: how well does each run's vessel image show the arteries it opacified?

For each phantom case folder (``geopose phantom --seed S --spacing-mm MM --out DIR/S``) and view, the NCC between the
run's vessel image as the registration makes it (``dsa.preprocess``: the bolus-weighted mean, clipped, on the TTO's
128-px detector) and the DRR of the phantom's opacified arteries (``truth.json``: early and late labels) at the true
pose. No registration runs: a view whose NCC is near 0 gives the TTO's vessel term nothing to align, even at the truth.

    .venv/bin/python experiments/vessel_image/residue_quality.py --folders /tmp/ph1 --seeds 6010-6034
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.cta.io import load_cta  # noqa: E402
from geopose.dsa import preprocess as P  # noqa: E402
from geopose.dsa.readers import read_dsa  # noqa: E402
from geopose.metrics.similarity import ncc  # noqa: E402
from geopose.options import TTO_PX_CPU  # noqa: E402
from geopose.register.evaluate import load_truth  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402
from geopose.render.volume import RenderVolume  # noqa: E402


def opacified_case(folder: Path):
    """A phantom case folder's CTA, a renderer whose vessel channel is the phantom's opacified arteries (the truth's
    early and late labels), and its truth."""
    cta = load_cta(folder / "cta.nii.gz")
    opacified = json.loads((folder / "truth.json").read_text())["opacified_labels"]
    labels = load_cta(folder / "labels.nii.gz", check_hu=False).array
    arteries = np.isin(labels, sorted(set(opacified["early"]) | set(opacified["late"])))
    return cta, TorchRenderer(RenderVolume(cta, {"vessels": cta.like(arteries.astype(np.uint8))})), load_truth(folder / "cta.nii.gz")


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folders", type=Path, required=True)
    ap.add_argument("--seeds", type=seed_range, required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    values = []
    for seed in args.seeds:
        folder = args.folders / str(seed)
        cta, renderer, truth = opacified_case(folder)
        row = {"seed": seed}
        for key in ("pa", "lat"):
            run = read_dsa(folder / f"dsa_{key}.dcm")
            frames = run.attenuation(None)
            mask = P.dsa_cranium_mask(P.temporal_map(frames))
            h, w = run.detector.shape
            scale = TTO_PX_CPU / max(h, w)
            detector = run.detector.resized(max(1, round(h * scale)), max(1, round(w * scale)))
            image = P.vessel_image(P.bolus_weighted_mean(frames, mask, run.detector.spacing_mm), mask, run.detector, detector)
            drr = renderer.render(truth.poses[key], detector, ("vessels",))[0]
            row[key] = round(ncc(image.astype(np.float64), drr.astype(np.float64)), 3)
            values.append(row[key])
        print(json.dumps(row), flush=True)
    print(f"views {len(values)}: mean NCC {np.mean(values):.3f}, min {np.min(values):.3f}, "
          f"below 0.3: {sum(v < 0.3 for v in values)}")


if __name__ == "__main__":
    main()
