"""Depth of the calibrated Init pose on four inputs of one view: the simulated DSA MAP
(what registration sees), a DRR of the same CTA at the true pose (model geometry), that
DRR masked by the MAP's cranium mask, and that DRR through the MAP's intensity chain
(docs/conventions.md 5: percentile clip, mask, bilateral, min-max); also the MAP with a milder
clip for the networks (``preprocess_dsa(model_clip_percentiles=...)``). Depth = the pose parameter
t_y (mm), the source-to-volume-centre distance along the central ray (docs/conventions.md 1-2).
The columns separate geometry from appearance and name the preprocessing step that the
network was not trained for. Held-out phantoms are written as DICOM/NIfTI and read back,
as in ``geopose bench``. Prints a Markdown table; ``--doc`` writes it.

    .venv/bin/python experiments/init_depth/bench_init_depth.py --seeds 5000-5019 --doc experiments/init_depth/init_depth.md
"""

from __future__ import annotations

import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: heldout.py
from heldout import parse_heldout_args, publish  # noqa: E402  (puts Logic/ on sys.path)

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.dsa.preprocess import bilateral, clip_intensities, minmax, preprocess_dsa  # noqa: E402
from geopose.geometry import params_from_pose  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import prepare_case  # noqa: E402
from geopose.render.renderer import NumpyRenderer  # noqa: E402
from geopose.register.calibration import calibrate, calibrated_init, render_model_view  # noqa: E402
from geopose.options import TTO_PX_CPU  # noqa: E402
from geopose.register.case import VIEW_KEYS  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402

#: Index of the depth component in the pose translation ``t`` (docs/conventions.md 2: isopose t = (0, 650, 0)).
DEPTH_AXIS = 1


def depth_mm(pose: np.ndarray) -> float:
    """``t_y`` (mm) of a camera-to-world pose ``(1, 4, 4)``."""
    return float(params_from_pose(np.asarray(pose, dtype=np.float64))[1][DEPTH_AXIS])


#: A milder clip of the MAP for the networks' input than docs/conventions.md 5's 25th-75th.
LOOSE_CLIP_PERCENTILES = (2.0, 98.0)
#: The inputs compared, in table order.
INPUTS = (
    "simulated DSA MAP (what registration sees)",
    f"the MAP clipped to its {LOOSE_CLIP_PERCENTILES[0]:g}th-{LOOSE_CLIP_PERCENTILES[1]:g}th percentiles instead",
    "DRR at the true pose",
    "the DRR masked by the MAP's cranium mask",
    "the DRR percentile-clipped and masked",
    "the DRR through the MAP's intensity chain (clip, mask, bilateral)",
)


def map_chain(drr: np.ndarray, mask: np.ndarray, smooth: bool = True) -> np.ndarray:
    """A model-geometry image ``(1, 1, H, W)`` through the MAP's intensities: percentile clip
    over the masked columns, mask, bilateral on an 8-bit scale (``smooth``), min-max."""
    clipped = clip_intensities(drr[0, 0], mask) * mask
    eight_bit = clipped / max(float(clipped.max()), 1e-6) * 255.0
    return minmax(bilateral(eight_bit) if smooth else eight_bit)[None, None]


def _summary(name: str, errors: np.ndarray, truth: np.ndarray, estimate: np.ndarray) -> str:
    corr = np.corrcoef(truth, estimate)[0, 1]
    return (f"| {name} | {errors.mean():+.1f} | {errors.std(ddof=1):.1f} | {np.abs(errors).mean():.1f} "
            f"| {corr:.2f} |")


def main() -> int:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "5000-5019")
    models = load_models(default_models_dir(), runtime="torch", device="cpu")
    init = models.init
    rows, table = [], []
    t0 = time.perf_counter()
    for i, seed in enumerate(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            case = phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm)
        prep = prepare_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels)
        renderer = NumpyRenderer(prep.volume)
        cal = calibrate(renderer, init, models.render_px)
        for key in VIEW_KEYS:
            true = case.true_poses[key]
            lateral = key == "lat"
            drr = render_model_view(renderer, true, models.render_px)
            mask = prep.views[key].model_mask
            loose = preprocess_dsa(case.runs[key], tto_px=TTO_PX_CPU, model_clip_percentiles=LOOSE_CLIP_PERCENTILES)
            images = (prep.model_target(key), loose.model_image[None, None], drr, drr * mask,
                      map_chain(drr, mask, smooth=False), map_chain(drr, mask))
            d = [depth_mm(true)] + [depth_mm(calibrated_init(x, lateral, init, cal).pose_native) for x in images]
            table.append(d)
            rows.append(f"| {seed} | {key.upper()} | {d[0]:.0f} | " + " | ".join(f"{v:.0f} ({v - d[0]:+.0f})" for v in d[1:]) + " |")
            print(f"[{i + 1}/{len(seeds)}] {rows[-1]}", file=sys.stderr, flush=True)
    truth, *estimates = np.asarray(table).T
    lines = [
        f"Shipped Init (`{default_models_dir().name}`), calibrated, {len(table)} views of {len(seeds)} held-out phantoms "
        f"at {args.spacing_mm:g} mm, {platform.processor() or platform.machine()}, "
        f"{args.threads} threads, {time.perf_counter() - t0:.0f} s.",
        "",
        "| Init input | depth error mean (mm) | sd | mean abs | correlation with true depth |",
        "|---|---:|---:|---:|---:|",
        *(_summary(name, est - truth, truth, est) for name, est in zip(INPUTS, estimates)),
        "",
        "| seed | view | true depth (mm) | Init on MAP (error) | on loosely clipped MAP | on DRR | on masked DRR | on clipped DRR | on DRR through the chain |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|",
        *rows,
    ]
    publish("\n".join(lines), args.doc, "Init depth: simulated DSA MAP vs DRR, and which preprocessing step makes the difference",
            "`experiments/init_depth/bench_init_depth.py`; what the numbers mean is in `docs/benchmark/bench.md` (Reading these numbers).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
