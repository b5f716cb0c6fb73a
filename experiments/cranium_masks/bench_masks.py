"""The two cranium masks the silhouette term compares, computed the user's way, against the
simulator's truth (experiments/cranium_masks/cranium_masks.md): the DSA cranium mask of each run (before: Otsu on the
MAP; after: the library's ``dsa_cranium_mask``) and the CTA cranium mask projected at the true pose,
on plain and densely opacified phantoms (``dense_runs.py``) and real head CTs with simulated runs.

    .venv/bin/python experiments/cranium_masks/bench_masks.py --seeds 5000-5007 --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --real-seeds 0-1 --threads 1 --doc experiments/cranium_masks/cranium_masks_table.md

Phantoms at 2 mm (``--spacing-mm``), runs at 512 px; about 1.5 min per phantom pair and 1 min per
real-head case on 2 cores.

Everything on the TTO detector (the acquisition SDD, 128 px along the longer side), where the
objective compares them. The truth of a run is the cranium the simulator drew, projected at the
true pose as ``simulate_dsa`` draws ``cranium_mask`` (path through it above 2 % of its maximum); the
projected CTA mask is what the objective's silhouette is (path through it above 0).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dense_runs import write_dense_phantom  # noqa: E402

from geopose.bench.cases import ge_head_case, headsq_case, seed_range  # noqa: E402
from geopose.cta import cranium_mask_from_cta, load_cta  # noqa: E402
from geopose.dsa import DSARun, read_dsa, temporal_map  # noqa: E402
from geopose.dsa.preprocess import _largest_component_filled, resample_to_detector  # noqa: E402
from geopose.images import block_mean  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402
from geopose.phantom.cli import write_phantom  # noqa: E402
from geopose.register.case import prepare_case, silhouette_dice  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402
from geopose.render.volume import RenderVolume  # noqa: E402
from geopose.volume import Volume  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

#: ``simulate_dsa``'s cranium_mask: the projected path above this fraction of its maximum.
TRUTH_FRACTION = 0.02


def otsu_on_map(image: np.ndarray, work_px: int = 256) -> np.ndarray:
    """The DSA cranium mask before 2026-12-04: Otsu on the block-averaged MAP, largest component, filled."""
    f = max(1, int(np.ceil(max(image.shape) / work_px)))
    small = block_mean(image, (f, f)) if f > 1 else image
    mask = _largest_component_filled(sitk.GetArrayFromImage(sitk.OtsuThreshold(sitk.GetImageFromArray(small), 0, 1)) > 0)
    return np.repeat(np.repeat(mask, f, 0), f, 1)[: image.shape[0], : image.shape[1]]


def measure(cta: Volume, truth_cranium: Volume, runs: dict[str, DSARun], poses: dict[str, np.ndarray]) -> list[dict]:
    """Per view: Dice against the truth and coverage of the DSA masks before / after, and of the CTA masks projected
    at the true pose (the automatic one and the truth's own), and the agreement the silhouette term sees."""
    prep = prepare_case(cta, runs)
    auto = TorchRenderer(prep.volume)
    truth = TorchRenderer(RenderVolume(cta, {"cranium": truth_cranium}))
    out = []
    for key, view in prep.views.items():
        det = view.tto_detector
        true_path = truth.render(poses[key], det, ("cranium",))[0]
        true_mask = true_path > TRUTH_FRACTION * true_path.max()
        before = resample_to_detector(otsu_on_map(temporal_map(runs[key].attenuation())).astype(np.float32),
                                      runs[key].detector, det) > 0.5
        after = view.tto_mask > 0
        cta_auto = auto.render(poses[key], det, ("cranium",))[0] > 0
        cta_truth = true_path > 0
        out.append({
            "dsa_before": silhouette_dice(before, true_mask), "dsa_after": silhouette_dice(after, true_mask),
            "cov_before": before.mean(), "cov_after": after.mean(), "cov_truth": true_mask.mean(),
            "cta_auto": silhouette_dice(cta_auto, true_mask), "cta_truth": silhouette_dice(cta_truth, true_mask),
            "agree_after": silhouette_dice(cta_auto, after), "agree_before": silhouette_dice(cta_auto, before),
            "agree_truth_cta": silhouette_dice(cta_truth, after),
        })
    return out


def _phantom(folder: Path) -> tuple[Volume, Volume, dict, dict, float]:
    cta = load_cta(folder / "cta.nii.gz")
    labels = load_cta(folder / "labels.nii.gz", check_hu=False)
    truth = json.loads((folder / "truth.json").read_text())
    cranium = labels.like(L.cranium_mask(labels.array).astype(np.uint8))
    runs = {key: read_dsa(folder / f"dsa_{key}.dcm") for key in ("pa", "lat")}
    poses = {key: np.asarray(truth["views"][key]["pose_camera_to_world"]) for key in ("pa", "lat")}
    volume_ratio = float(cranium_mask_from_cta(cta).array.sum() / cranium.array.sum())
    return cta, cranium, runs, poses, volume_ratio


COLUMNS = [
    ("DSA mask Dice, before", "dsa_before"), ("after", "dsa_after"),
    ("coverage before", "cov_before"), ("after", "cov_after"), ("truth", "cov_truth"),
    ("CTA auto projected, Dice vs truth", "cta_auto"), ("CTA truth projected", "cta_truth"),
    ("agreement CTA auto vs DSA before", "agree_before"), ("vs DSA after", "agree_after"),
]


def table(rows: list[tuple[str, str, list[dict], float | None]]) -> list[str]:
    lines = ["| case | group | " + " | ".join(c for c, _ in COLUMNS) + " | CTA auto / label volume |",
             "|---|---|" + "---:|" * (len(COLUMNS) + 1)]
    for name, group, views, ratio in rows:
        cells = [" / ".join(f"{v[k]:.2f}" for v in views) for _, k in COLUMNS]
        lines.append(f"| {name} | {group} | " + " | ".join(cells) + f" | {'' if ratio is None else f'{ratio:.2f}'} |")
    lines += ["", "| group (views) | " + " | ".join(c for c, _ in COLUMNS) + " |", "|---|" + "---:|" * len(COLUMNS)]
    for group in dict.fromkeys(g for _, g, _, _ in rows):
        views = [v for _, g, vs, _ in rows if g == group for v in vs]
        cells = [f"{np.mean([v[k] for v in views]):.3f} (min {np.min([v[k] for v in views]):.2f})" for _, k in COLUMNS]
        lines.append(f"| {group} ({len(views)}) | " + " | ".join(cells) + " |")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seed_range, default=seed_range("6000-6009"))
    ap.add_argument("--headsq")
    ap.add_argument("--ge-head")
    ap.add_argument("--real-seeds", type=seed_range, default=seed_range("0-1"))
    ap.add_argument("--spacing-mm", type=float, default=2.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--doc", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows, t0 = [], time.perf_counter()

    def done(name: str, group: str, views: list[dict], ratio: float | None) -> None:
        rows.append((name, group, views, ratio))
        print(table(rows[-1:])[2], f"({(time.perf_counter() - t0) / 60:.1f} min)", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for group, write in (("phantom normal", write_phantom), ("phantom dense", write_dense_phantom)):
                folder = Path(tmp) / f"{group}-{seed}"
                write(seed, folder, spacing_mm=args.spacing_mm, max_matrix_px=512)
                cta, cranium, runs, poses, ratio = _phantom(folder)
                done(f"{group.split()[1]}-{seed}", group, measure(cta, cranium, runs, poses), ratio)
    for path, make in ((args.headsq, headsq_case), (args.ge_head, ge_head_case)):
        for arteries in (False, True):
            for seed in (args.real_seeds if path else []):
                case = make(path, seed=seed, arteries=arteries)
                done(case.name, "real head " + ("+arteries" if arteries else "plain"),
                     measure(case.cta, case.cranium, case.runs, case.true_poses), None)
    lines = table(rows)
    print("\n".join(lines))
    if args.doc:
        args.doc.write_text("python experiments/cranium_masks/bench_masks.py " + " ".join(sys.argv[1:]) + "\n\nPer case: PA / LAT.\n\n"
                            + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
