"""Shared command line of the benchmarks on held-out phantom subjects: seed ranges
(refused if the shipped models were trained on them), phantom spacing, threads, and the
Markdown document the table goes to."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Logic"))

from geopose.bench.cases import seed_range, training_seeds  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402


def parse_heldout_args(description: str, default_seeds: str) -> tuple[argparse.Namespace, list[int]]:
    """Parse ``--seeds --spacing-mm --iterations --threads --doc``, set torch's threads, and return the
    arguments with the sorted held-out seeds; exits with the remedy on a training seed."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--seeds", nargs="+", type=seed_range, default=[seed_range(default_seeds)],
                    help=f"ranges such as {default_seeds}")
    ap.add_argument("--spacing-mm", type=float, default=2.0, help="phantom voxel spacing (mm)")
    ap.add_argument("--iterations", type=int, default=25, help="TTO steps, where a benchmark runs the TTO")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=None, help="Markdown file to write the tables to")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    seeds = sorted({s for group in args.seeds for s in group})
    clash = training_seeds(default_models_dir() / "manifest.json") & set(seeds)
    if clash:
        raise SystemExit(f"seeds {sorted(clash)} were used to train the shipped models: choose held-out seeds")
    return args, seeds


def publish(table: str, doc: Path | None, title: str, intro: str) -> None:
    """Print ``table``; with ``doc``, write it there under ``# title`` and ``intro``."""
    print(table)
    if doc:
        doc.write_text(f"# {title}\n\n{intro}\n\n{table}\n")
