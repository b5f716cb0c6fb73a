"""Depth of the calibrated Init pose: on the simulated DSA MAP against on a DRR of the
same CTA rendered at the true pose (model geometry). Depth = the pose parameter t_y
(mm), the source-to-volume-centre distance along the central ray (CONVENTIONS 1-2).
If the DRR column is right and the MAP column is not, the error is the MAP-vs-DRR
appearance gap of the trained network, not geometry. Held-out phantoms are written as
DICOM/NIfTI and read back, as in ``geopose bench``. Prints a Markdown table; ``--doc``
writes it.

    .venv/bin/python benchmarks/bench_init_depth.py --seeds 5000-5019 --doc docs/init_depth.md
"""

from __future__ import annotations

import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from heldout import parse_heldout_args, publish  # puts Logic/ on sys.path

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.geometry import params_from_pose  # noqa: E402
from geopose.nets import make_predictors  # noqa: E402
from geopose.register import RegistrationOptions, prepare_case  # noqa: E402
from geopose.register.calibration import calibrate, calibrated_init, render_model_view  # noqa: E402
from geopose.register.case import VIEW_KEYS  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402

#: Index of the depth component in the pose translation ``t`` (CONVENTIONS 2: isopose t = (0, 650, 0)).
DEPTH_AXIS = 1


def depth_mm(pose: torch.Tensor) -> float:
    """``t_y`` (mm) of a camera-to-world pose ``(1, 4, 4)``."""
    return float(params_from_pose(pose.double())[1][0, DEPTH_AXIS])


def _summary(name: str, errors: np.ndarray, truth: np.ndarray, estimate: np.ndarray) -> str:
    corr = np.corrcoef(truth, estimate)[0, 1]
    return (f"| {name} | {errors.mean():+.1f} | {errors.std(ddof=1):.1f} | {np.abs(errors).mean():.1f} "
            f"| {corr:.2f} |")


def main() -> int:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "5000-5019")
    init, _ = make_predictors(default_models_dir(), backend="torch", device="cpu")
    rows, table = [], []
    t0 = time.perf_counter()
    for i, seed in enumerate(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            case = phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm)
        prep = prepare_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels,
                            options=RegistrationOptions())
        cal = calibrate(prep.drr, init)
        for key in VIEW_KEYS:
            true = torch.as_tensor(case.true_poses[key], dtype=torch.float64)[None]
            lateral = key == "lat"
            on_map = calibrated_init(prep.model_target(key), lateral, init, cal)
            with torch.no_grad():
                on_drr = calibrated_init(render_model_view(prep.drr, true.float()), lateral, init, cal)
            d = (depth_mm(true), depth_mm(on_map.pose_native), depth_mm(on_drr.pose_native))
            table.append(d)
            rows.append(f"| {seed} | {key.upper()} | {d[0]:.0f} | {d[1]:.0f} ({d[1] - d[0]:+.0f}) | {d[2]:.0f} ({d[2] - d[0]:+.0f}) |")
            print(f"[{i + 1}/{len(seeds)}] {rows[-1]}", file=sys.stderr, flush=True)
    truth, on_map, on_drr = np.asarray(table).T
    lines = [
        f"Shipped Init (`{default_models_dir().name}`), calibrated, {len(table)} views of {len(seeds)} held-out phantoms "
        f"at {args.spacing_mm:g} mm, torch {torch.__version__}, {platform.processor() or platform.machine()}, "
        f"{args.threads} threads, {time.perf_counter() - t0:.0f} s.",
        "",
        "| Init input | depth error mean (mm) | sd | mean abs | correlation with true depth |",
        "|---|---:|---:|---:|---:|",
        _summary("simulated DSA MAP (what registration sees)", on_map - truth, truth, on_map),
        _summary("DRR at the true pose", on_drr - truth, truth, on_drr),
        "",
        "| seed | view | true depth (mm) | Init on MAP (error) | Init on DRR (error) |",
        "|---:|---|---:|---:|---:|",
        *rows,
    ]
    publish("\n".join(lines), args.doc, "Init depth: simulated DSA MAP vs DRR",
            "`benchmarks/bench_init_depth.py`; what the numbers mean is in `docs/benchmark/bench.md` (Reading these numbers).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
