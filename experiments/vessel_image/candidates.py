"""Can the CTA pick a run's vessel image? Several temporal weightings of each run, and the one whose NCC with the
DRR of the CTA's computed vessel mask at a pose a few mm off the truth (the networks' estimate lies 2-3 mm off) is
highest.

For each phantom case folder (``geopose phantom --seed S --spacing-mm MM --out DIR/S``) and view, each candidate
vessel image (``dsa.preprocess.vessel_image`` of a weighted mean of the frames, on the TTO's 128 px detector) is
scored twice: by the truth (NCC with the DRR of the phantom's opacified arteries at the true pose, as
``residue_quality.py``) and by what a registration has (NCC with the DRR of ``cta.vessel_mask_from_cta`` at the true
pose moved by ``--turn-deg`` about a random axis through the head's centre and ``--shift-mm`` in a random direction,
the same draw for both views of a case). The run's first half is picked where its second NCC beats the bolus
weighting's by ``--margin`` (the plain mean is scored, not picked: ``PICKED_FROM``). One JSON line per case; the summary gives each candidate's mean truth
NCC, the picked one's, and how often the pick was within 0.01 of the truth's best.

    .venv/bin/python experiments/vessel_image/candidates.py --folders /tmp/ph1 --seeds 6010-6034
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.cta import vessel_mask_from_cta  # noqa: E402
from geopose.dsa import preprocess as P  # noqa: E402
from geopose.dsa.readers import read_dsa  # noqa: E402
from geopose.geometry.poses import axis_angle_to_matrix  # noqa: E402
from geopose.metrics.similarity import ncc  # noqa: E402
from geopose.options import TTO_PX_CPU  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402
from geopose.render.volume import RenderVolume  # noqa: E402
from residue_quality import opacified_case  # noqa: E402


def candidate_weights(frames: np.ndarray, mask: np.ndarray, pixel_mm) -> dict[str, np.ndarray]:
    """Frame weights ``(T,)`` per candidate: the product's bolus weighting, the plain mean and the first half of the run
    (the arteries come before the capillary blush)."""
    T = len(frames)
    bolus = P.bolus_weighted_mean(frames, mask, pixel_mm)
    # the product's weights, recovered from its weighted mean (least squares over a pixel sample)
    sample = frames.reshape(T, -1)[:, ::97].astype(np.float64)
    w_bolus, *_ = np.linalg.lstsq(sample.T, bolus.reshape(-1)[::97].astype(np.float64), rcond=None)
    early = np.zeros(T)
    early[: max(1, (T + 1) // 2)] = 1.0
    return {"bolus": np.clip(w_bolus, 0.0, None), "mean": np.ones(T), "early_half": early}


#: The candidates a pick chooses from. The plain mean is scored but not picked: in runs with a venous phase it matches
#: the computed mask's veins best and shows the arteries worst (candidates.md).
PICKED_FROM = ("bolus", "early_half")


def moved(pose: np.ndarray, turn: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    """Camera-to-world ``pose`` with the head turned by ``turn`` (axis-angle, rad) about the centre and shifted."""
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(turn)
    T[:3, 3] = shift_mm
    return T @ pose


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folders", type=Path, required=True)
    ap.add_argument("--seeds", type=seed_range, required=True)
    ap.add_argument("--turn-deg", type=float, default=2.0)
    ap.add_argument("--shift-mm", type=float, default=3.0)
    ap.add_argument("--margin", type=float, default=0.05, help="another candidate is picked only when its NCC with the "
                    "CTA's vessels beats the bolus weighting's by this")
    args = ap.parse_args()
    torch.set_num_threads(2)
    rng = np.random.default_rng(52)
    truth_scores: dict[str, list[float]] = {}
    picked, best_hits, views = [], 0, 0
    for seed in args.seeds:
        folder = args.folders / str(seed)
        cta, oracle, truth = opacified_case(folder)
        computed = TorchRenderer(RenderVolume(cta, {"vessels": vessel_mask_from_cta(cta)}))
        axis = rng.normal(size=3)
        turn = np.radians(args.turn_deg) * axis / np.linalg.norm(axis)
        direction = rng.normal(size=3)
        shift = args.shift_mm * direction / np.linalg.norm(direction)
        row: dict = {"seed": seed}
        for key in ("pa", "lat"):
            run = read_dsa(folder / f"dsa_{key}.dcm")
            frames = np.asarray(run.attenuation(None), dtype=np.float32)
            mask = P.dsa_cranium_mask(P.temporal_map(frames))
            h, w = run.detector.shape
            scale = TTO_PX_CPU / max(h, w)
            detector = run.detector.resized(max(1, round(h * scale)), max(1, round(w * scale)))
            true_drr = oracle.render(truth.poses[key], detector, ("vessels",))[0].astype(np.float64)
            seen_drr = computed.render(moved(truth.poses[key], turn, shift), detector, ("vessels",))[0].astype(np.float64)
            scores = {}
            for name, weights in candidate_weights(frames, mask, run.detector.spacing_mm).items():
                if not weights.sum() > 0:
                    continue
                image = np.tensordot((weights / weights.sum()).astype(np.float32), frames, axes=1)
                vessels = P.vessel_image(image, mask, run.detector, detector).astype(np.float64)
                scores[name] = (round(ncc(vessels, true_drr), 3), round(ncc(vessels, seen_drr), 3))
                truth_scores.setdefault(name, []).append(scores[name][0])
            pick = max(PICKED_FROM, key=lambda n: scores[n][1] - (0.0 if n == "bolus" else args.margin))
            best = max(scores, key=lambda n: scores[n][0])
            picked.append(scores[pick][0])
            best_hits += scores[pick][0] >= scores[best][0] - 0.01
            views += 1
            row[key] = {"scores (truth, seen)": scores, "picked": pick}
        print(json.dumps(row), flush=True)
    for name, values in truth_scores.items():
        print(f"{name:12s} mean truth NCC {np.mean(values):.3f}  min {np.min(values):.3f}  below 0.3: {sum(v < 0.3 for v in values)}")
    print(f"picked       mean truth NCC {np.mean(picked):.3f}  min {np.min(picked):.3f}  below 0.3: "
          f"{sum(v < 0.3 for v in picked)}; within 0.01 of the truth's best in {best_hits} of {views} views")


if __name__ == "__main__":
    main()
