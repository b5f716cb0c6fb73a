"""Stage times of one registration on CUDA next to the paper's H100 figures and to the same registration on
the CPU, and how far apart the two engines' final poses are.

    python benchmarks/gpu_compare.py --cuda R_CUDA/result.json --cpu R_CPU/result.json [--doc gpu_check.md]

The records are ``geopose register`` outputs of the same case (``runtimes_s``, per view ``pose_centred`` and,
for a phantom, ``truth``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

#: The paper's H100 figures (s) for the stages this pipeline also has (GeoPose paper, runtime paragraph).
PAPER_S = {"init": 0.0218, "refine": 0.147, "tto": 2.0}


def _pose_gap(a: list, b: list) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) between two 4 x 4 poses (centred frame)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    r = a[:3, :3].T @ b[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
    return float(angle), float(np.linalg.norm(a[:3, 3] - b[:3, 3]))


def table(cuda: dict, cpu: dict) -> list[str]:
    lines = ["| stage | CUDA s | CPU s | paper H100 s |", "|---|---:|---:|---:|"]
    for stage, seconds in cuda["runtimes_s"].items():
        paper = PAPER_S.get(stage)
        lines.append(f"| {stage} | {seconds:.3f} | {cpu['runtimes_s'].get(stage, float('nan')):.3f} | "
                     f"{'-' if paper is None else f'{paper:g}'} |")
    lines += ["", "| view | CUDA vs CPU final pose: rotation deg | translation mm | mPCD CUDA / CPU mm |", "|---|---:|---:|---|"]
    for key in ("pa", "lat"):
        rot, mm = _pose_gap(cuda["views"][key]["pose_centred"], cpu["views"][key]["pose_centred"])
        truth = [run["views"][key].get("truth", {}).get("final", {}).get("mpcd_mm") for run in (cuda, cpu)]
        mpcd = " / ".join("-" if t is None else f"{t:.2f}" for t in truth)
        lines.append(f"| {key} | {rot:.3f} | {mm:.2f} | {mpcd} |")
    lines.append("")
    lines.append(f"engines: CUDA {cuda['engine'].get('device')} tto_px {cuda['engine'].get('tto_px')}; "
                 f"CPU {cpu['engine'].get('device')} tto_px {cpu['engine'].get('tto_px')}")
    return lines


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cuda", required=True, help="result.json of the CUDA registration")
    p.add_argument("--cpu", required=True, help="result.json of the CPU registration")
    p.add_argument("--doc", help="also write the tables here (markdown)")
    args = p.parse_args()
    lines = table(json.loads(Path(args.cuda).read_text()), json.loads(Path(args.cpu).read_text()))
    print("\n".join(lines))
    if args.doc:
        Path(args.doc).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
