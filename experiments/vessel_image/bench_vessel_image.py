"""How faithful is each run's vessel image (what the TTO's vessel term aligns the CTA's vessels on)?
Per held-out phantom and view: the NCC, at the true pose, between the run's vessel image
(``dsa.preprocess.vessel_image`` of the frames weighted by the bolus) and the DRR of the arteries the
run opacifies (the phantom's labels: scoring only). Frame weightings compared:

* ``detail``: the library's ``bolus_weighted_mean`` (the curve read from the frames' fine detail);
* ``plain frames``: the curve read from the plain frames' brightest pixels (the rule until 2026-12-05);
* ``mean``: every frame alike.

    .venv/bin/python experiments/vessel_image/bench_vessel_image.py --seeds 6010-6029 --doc experiments/vessel_image/vessel_image_table.md
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import parse_heldout_args, publish  # noqa: E402

from geopose import contract as C  # noqa: E402
from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.cta import load_cta  # noqa: E402
from geopose.dsa.preprocess import bolus_weighted_mean, preprocess_dsa, vessel_image  # noqa: E402
from geopose.metrics.similarity import ncc  # noqa: E402
from geopose.render.drr import DRR  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

WEIGHTINGS = ("detail", "plain frames", "mean")


def plain_frames_weighted(frames: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The frames weighted by the curve of the plain frames' brightest pixels (the previous rule)."""
    inside = mask > 0
    mean = frames.mean(axis=0)
    bright = inside & (mean >= np.percentile(mean[inside], C.BOLUS_PIXEL_PERCENTILE))
    curve = frames[:, bright].mean(axis=1, dtype=np.float64)
    weights = np.clip(curve - np.median(curve), 0.0, None)
    return mean if not weights.sum() > 0 else np.tensordot((weights / weights.sum()).astype(np.float32), frames, axes=1)


def case_rows(seed: int, spacing_mm: float) -> dict:
    folder = Path(tempfile.mkdtemp())
    case = phantom_case(seed, folder, spacing_mm)
    truth = json.loads((folder / "truth.json").read_text())
    opacified = truth["opacified_labels"]
    labels = load_cta(folder / "labels.nii.gz", check_hu=False)
    arteries = labels.like(np.isin(labels.array, opacified["early"] + opacified["late"]).astype(np.uint8))
    drr = DRR.from_volume(case.cta, case.runs["pa"].detector, labels=arteries, label_groups={"arteries": [1]})
    row = {"seed": seed, "injection": truth.get("injection")}
    for key in ("pa", "lat"):
        run = case.runs[key]
        prepared = preprocess_dsa(run)
        with torch.no_grad():
            reference = drr(torch.as_tensor(case.true_poses[key][None]), detector=prepared.tto_detector, channels=[1])[0, 0].numpy()
        frames = run.attenuation(None).astype(np.float32)
        images = {"detail": bolus_weighted_mean(frames, prepared.mask, run.detector.spacing_mm),
                  "plain frames": plain_frames_weighted(frames, prepared.mask), "mean": frames.mean(axis=0)}
        row[key] = {name: round(ncc(vessel_image(image, prepared.mask, run.detector, prepared.tto_detector), reference), 3)
                    for name, image in images.items()}
    return row


def main() -> None:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "6010-6029")
    rows = []
    for seed in seeds:
        rows.append(case_rows(seed, args.spacing_mm))
        print(json.dumps(rows[-1]), flush=True)
    lines = [f"`{' '.join(sys.argv)}`", "",
             "NCC at the true pose of the run's vessel image with the DRR of its opacified arteries:", "",
             "| seed | injection | " + " | ".join(f"{v.upper()} {w}" for v in ("pa", "lat") for w in WEIGHTINGS) + " |",
             "|---|---|" + "---:|" * (2 * len(WEIGHTINGS))]
    lines += [f"| {r['seed']} | {r['injection']} | " + " | ".join(f"{r[v][w]:.3f}" for v in ("pa", "lat") for w in WEIGHTINGS) + " |"
              for r in rows]
    values = {w: np.array([r[v][w] for r in rows for v in ("pa", "lat")]) for w in WEIGHTINGS}
    lines += ["", "| weighting | mean NCC | min | views below 0.5 |", "|---|---:|---:|---:|"]
    lines += [f"| {w} | {x.mean():.3f} | {x.min():.3f} | {(x < 0.5).sum()} of {x.size} |" for w, x in values.items()]
    publish("\n".join(lines), args.doc, "Fidelity of the runs' vessel images", "Held-out phantoms, 2 mm; see vessel_image.md.")


if __name__ == "__main__":
    main()
