"""Time one full GeoPose registration (calibration, both views, greedy refinement,
TTO) on a phantom case with the shipped models; prints a Markdown table and
optionally writes it into a doc.

    .venv/bin/python benchmarks/bench_pipeline.py --threads 2 --device cpu --doc docs/pipeline_benchmark.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Logic"))

from geopose import contract as C  # noqa: E402
from geopose.phantom.cli import write_phantom  # noqa: E402
from geopose.register.cli import register_files  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402

#: The paper's H100 runtimes (CONVENTIONS section 7), for comparison.
PAPER_MS = {"calibration + init": 21.8, "refine": 147.0, "tto": 2000.0}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=20260)
    ap.add_argument("--iterations", type=int, default=C.TTO_ITERATIONS)
    ap.add_argument("--tto-px", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        case = Path(tmp) / "case"
        write_phantom(args.seed, case)
        runs = []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            rec = register_files(
                case / "cta.nii.gz", case / "dsa_pa.dcm", case / "dsa_lat.dcm", Path(tmp) / f"out{r}",
                options=RegistrationOptions(iterations=args.iterations, tto_px=args.tto_px, device=args.device),
                progress=lambda *a: None,
            )
            rec["runtimes_s"]["wall incl. file reading and record"] = time.perf_counter() - t0
            runs.append(rec["runtimes_s"])
    best = {k: min(r[k] for r in runs) for k in runs[0]}
    load = os.getloadavg()[0]
    lines = [
        f"Device `{args.device}` ({platform.machine()}), torch {torch.__version__}, {args.threads} threads; phantom seed "
        f"{args.seed} (256^3 at 1 mm), shipped models, {args.iterations} TTO iterations; best of {args.repeats}; "
        f"1-min load average at the end {load:.2f}.",
        "",
        "| stage | seconds |",
        "|---|---:|",
    ] + [f"| {k} | {v:.2f} |" for k, v in best.items()]
    table = "\n".join(lines)
    print(table)
    if args.doc:
        marker = f"<!-- bench:{args.device} -->"
        text = args.doc.read_text() if args.doc.is_file() else "# Pipeline benchmark\n\nReproduce: `.venv/bin/python benchmarks/bench_pipeline.py --threads 2 --device cpu --doc docs/pipeline_benchmark.md`\n"
        if marker in text:
            head, rest = text.split(marker, 1)
            tail = rest.split("<!-- end -->", 1)[1] if "<!-- end -->" in rest else ""
            text = head + marker + "\n" + table + "\n<!-- end -->" + tail
        else:
            text += f"\n{marker}\n{table}\n<!-- end -->\n"
        args.doc.write_text(text)
        (args.doc.with_suffix(f".{args.device}.json")).write_text(json.dumps({"runs": runs, "load": load}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
