"""Calibration + Init + greedy Refine with and without PyTorch on one phantom case:
per-stage seconds of ``register_case`` (torch, no TTO) and ``register_case_numpy``
(numpy renderer + onnxruntime, at 128 px and at the full 256 px), and how far the
torch-free poses lie from the torch ones. Prints a Markdown table; ``--doc`` writes it.

    .venv/bin/python benchmarks/bench_torch_free.py --threads 2 --doc docs/torch_free_benchmark.md
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Logic"))

from geopose.cta import load_cta  # noqa: E402
from geopose.dsa import read_dsa  # noqa: E402
from geopose.geometry.numpy_poses import rotation_angle_rad  # noqa: E402
from geopose.nets import make_predictors  # noqa: E402
from geopose.phantom.cli import write_phantom  # noqa: E402
from geopose.register import RegistrationOptions, register_case, register_case_numpy  # noqa: E402
from geopose.register.record import as_numpy  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402

STAGES = ("prepare", "calibration", "init", "refine", "total")
MARKER = "<!-- bench:torch-free -->"


def _final(result, key: str) -> np.ndarray:
    return as_numpy(result.views[key].final_pose).reshape(4, 4)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=20260)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        write_phantom(args.seed, Path(tmp))
        cta = load_cta(Path(tmp) / "cta.nii.gz")
        runs = {key: read_dsa(Path(tmp) / f"dsa_{key}.dcm") for key in ("pa", "lat")}
        init, refine = make_predictors(default_models_dir(), "torch")
        engines = {
            "torch (256 px renders)": lambda: register_case(
                cta, runs, init=init, refine=refine, options=RegistrationOptions(iterations=0, device="cpu")
            ),
            "numpy + onnxruntime, 128 px": lambda: register_case_numpy(cta, runs),
            "numpy + onnxruntime, 256 px": lambda: register_case_numpy(cta, runs, render_px=256),
        }
        results, times = {}, {}
        for name, run in engines.items():
            best = None
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                result = run()
                wall = time.perf_counter() - t0
                if best is None or wall < best[0]:
                    best = (wall, result)
            results[name], times[name] = best[1], best[1].runtimes_s
    reference = results["torch (256 px renders)"]
    lines = [
        f"CPU ({platform.machine()}), {args.threads} threads, torch {torch.__version__}; phantom seed {args.seed} "
        f"(256^3 at 1 mm), shipped models, no TTO; best of {args.repeats}; 1-min load average at the end "
        f"{os.getloadavg()[0]:.2f}.",
        "",
        "| engine | " + " | ".join(f"{s} (s)" for s in STAGES) + " | PA / LAT final pose vs torch (mm, deg) |",
        "|---|" + "---:|" * len(STAGES) + "---|",
    ]
    for name, result in results.items():
        moved = []
        for key in ("pa", "lat"):
            a, b = _final(result, key), _final(reference, key)
            moved.append(f"{np.linalg.norm(a[:3, 3] - b[:3, 3]):.2f}, {np.degrees(rotation_angle_rad(a[:3, :3].T @ b[:3, :3])):.2f}")
        lines.append(f"| {name} | " + " | ".join(f"{times[name][s]:.2f}" for s in STAGES) + f" | {' / '.join(moved)} |")
    table = "\n".join(lines)
    print(table)
    if args.doc:
        text = args.doc.read_text() if args.doc.is_file() else MARKER + "\n"
        head = text.split(MARKER)[0]
        args.doc.write_text(head + MARKER + "\n" + table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
