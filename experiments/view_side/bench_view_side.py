"""Lateral side (LAT- / LAT+) decided by the shipped Init network on held-out phantom
lateral runs: the published single-image rule against the mirror-averaged logits
(``geopose.nets.mirror_averaged_logits``). Each subject is written as DICOM/NIfTI and
read back, as in ``geopose bench``; the true side comes from the run's primary angle.
Prints a Markdown table; ``--doc`` writes it.

    .venv/bin/python experiments/view_side/bench_view_side.py --seeds 5000-5039 6000-6029 --doc experiments/view_side/view_side.md
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

from geopose import contract as C  # noqa: E402
from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.dsa import preprocess_dsa  # noqa: E402
from geopose.options import TTO_PX_CPU  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first


def side_margins(init, target: np.ndarray) -> tuple[float, float]:
    """LAT+ minus LAT- logit of the single image and of the mirror-averaged logits."""
    _, _, single = init.predict(target, True, mirror=False)
    _, _, mirrored = init.predict(target, True, mirror=True)
    margin = lambda logits: float(logits[0, C.VIEW_LAT_PLUS] - logits[0, C.VIEW_LAT_MINUS])  # noqa: E731
    return margin(single), margin(mirrored)


def main() -> int:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "5000-5039")
    init = load_models(default_models_dir(), runtime="torch", device="cpu").init
    rows, right = [], {"single": 0, "mirror": 0}
    t0 = time.perf_counter()
    for i, seed in enumerate(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            case = phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm)
        run = case.runs["lat"]
        target = preprocess_dsa(run, tto_px=TTO_PX_CPU).model_image[None, None].astype(np.float32)
        true_side = run.view_label
        single, mirror = side_margins(init, target)
        verdict = {}
        for rule, m in (("single", single), ("mirror", mirror)):
            side = C.VIEW_LAT_PLUS if m > 0 else C.VIEW_LAT_MINUS
            verdict[rule] = side == true_side
            right[rule] += verdict[rule]
        rows.append(
            f"| {seed} | {C.VIEW_NAMES[true_side]} | {single:+.2f} | {'yes' if verdict['single'] else '**no**'} "
            f"| {mirror:+.2f} | {'yes' if verdict['mirror'] else '**no**'} |"
        )
        print(f"[{i + 1}/{len(seeds)}] {rows[-1]}", file=sys.stderr, flush=True)
    n = len(seeds)
    lines = [
        f"Shipped Init (`{default_models_dir().name}`), {n} held-out phantom lateral runs at {args.spacing_mm:g} mm, "
        f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {args.threads} threads, "
        f"{time.perf_counter() - t0:.0f} s. Margin = LAT+ minus LAT- logit (positive: LAT+).",
        "",
        "| rule | side right | accuracy |",
        "|---|---:|---:|",
        f"| single image (published) | {right['single']}/{n} | {100 * right['single'] / n:.1f} % |",
        f"| mirror-averaged (shipped default) | {right['mirror']}/{n} | {100 * right['mirror'] / n:.1f} % |",
        "",
        "| seed | true side | single-image margin | right | mirror-averaged margin | right |",
        "|---:|---|---:|---|---:|---|",
        *rows,
    ]
    publish("\n".join(lines), args.doc, "Lateral side: single image vs mirror-averaged logits",
            "`experiments/view_side/bench_view_side.py`; the rule is described in docs/method.md.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
