"""Shared command line of the benchmarks on held-out phantom subjects: seed ranges
(refused if the shipped models were trained on them), phantom spacing, threads, and the
Markdown document the table goes to; and the loop over real-head cases and phantoms that
the per-case benchmarks share."""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator, TextIO

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Logic"))

import geopose  # noqa: E402,F401  (before torch: its OpenMP threads then sleep when idle, geopose.OPENMP_THREADS_SLEEP)
import numpy as np  # noqa: E402
import torch  # noqa: E402

from geopose.bench.cases import (  # noqa: E402,F401  (flipped_left_right: for the experiments that import it from here)
    BenchCase, flipped_left_right, ge_head_case, headsq_case, phantom_case, seed_range, training_seeds)
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


def heldout_phantoms(description: str, default_seeds: str) -> Iterator[tuple[argparse.Namespace, BenchCase, TextIO]]:
    """For the scripts that write one JSON line per held-out phantom: parse the arguments
    (:func:`parse_heldout_args`), then yield ``(args, case, out)`` per seed, each phantom written to a temporary
    folder, ``out`` the ``--doc`` file (else stdout)."""
    args, seeds = parse_heldout_args(description, default_seeds)
    out = open(args.doc, "w") if args.doc else sys.stdout
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            yield args, phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm), out


def written_correct_and_mirrored(folders: Path, first: int, last: int) -> Iterator[tuple[int, str, object, dict]]:
    """Per phantom folder ``folders/SEED`` (``first``..``last``, as ``geopose phantom`` writes them) its CTA as written
    and mirrored left-right (:func:`flipped_left_right`) with its two runs: ``(seed, "correct" | "mirrored", cta,
    runs)``."""
    from geopose.cta.io import load_cta
    from geopose.dsa.readers import read_dsa

    for seed in range(first, last + 1):
        cta = load_cta(folders / str(seed) / "cta.nii.gz")
        runs = {k: read_dsa(folders / str(seed) / f"dsa_{k}.dcm") for k in ("pa", "lat")}
        for name, c in (("correct", cta), ("mirrored", flipped_left_right(cta))):
            yield seed, name, c, runs


def view_errors(case, poses: dict) -> dict:
    """Per view ``(carotid mPCD at the detector, mm; rotation error, deg)`` of ``poses`` ``{view: (4, 4)}`` against the
    phantom's truth; ``case`` holds ``true_poses``, ``runs`` and ``carotid_points_mm`` (a :class:`BenchCase`)."""
    from geopose.metrics.measures import pose_error_components
    from geopose.register.evaluate import carotid_mpcd

    out = {}
    for k in ("pa", "lat"):
        m = carotid_mpcd(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                         case.carotid_points_mm)[0].detector_mm
        p = pose_error_components(poses[k], case.true_poses[k])
        out[k] = (round(m, 3), round(float(np.hypot(p["in_plane_rotation_deg"], p["out_of_plane_rotation_deg"])), 3))
    return out


def error_cell(err: tuple[float, float, float | None]) -> str:
    """``rotation (deg) / source position (mm) [/ mPCD (mm)]`` of one case's errors."""
    rot, src, mpcd = err
    return f"{rot:.2f} / {src:.1f}" + ("" if mpcd is None else f" / {mpcd:.2f}")


def run_cases(description: str, default_seeds: str, default_threads: int,
              measure: Callable[[BenchCase], list]) -> tuple[argparse.Namespace, list[tuple[BenchCase, list]]]:
    """Parse ``--headsq --ge-head --real-seeds --seeds --spacing-mm --threads --doc``, build the real-head
    cases (plain, then with arteries, per head) and the held-out phantoms one at a time, and return the
    arguments with ``(case, measure(case))`` per case (``measure`` gives cells of :func:`error_cell`'s form;
    each row is printed to stderr as it comes)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--headsq", help="headsq quarter_sidecar.mhd")
    ap.add_argument("--ge-head", help="the GE head CT DICOM folder")
    ap.add_argument("--real-seeds", type=seed_range, default=seed_range("0-2"), help="real-head case seeds, e.g. 0-2")
    ap.add_argument("--seeds", nargs="*", type=seed_range, default=[seed_range(s) for s in default_seeds.split()],
                    help=f"held-out phantom seed ranges, e.g. {default_seeds}")
    ap.add_argument("--spacing-mm", type=float, default=2.0, help="phantom voxel spacing (mm)")
    ap.add_argument("--threads", type=int, default=default_threads)
    ap.add_argument("--doc", type=Path, default=None, help="Markdown file to write the table to")
    args = ap.parse_args()
    seeds = [s for group in args.seeds for s in group]
    clash = training_seeds(default_models_dir() / "manifest.json") & set(seeds)
    if clash:
        raise SystemExit(f"seeds {sorted(clash)} were used to train the shipped models: choose held-out seeds")
    torch.set_num_threads(args.threads)
    rows: list[tuple[BenchCase, list]] = []
    t0 = time.perf_counter()

    def cases(tmp: Path):
        for path, make in ((args.headsq, headsq_case), (args.ge_head, ge_head_case)):
            for arteries in (False, True):
                for seed in (args.real_seeds if path else []):
                    yield make(path, seed=seed, arteries=arteries)
        for seed in seeds:
            yield phantom_case(seed, tmp / str(seed), args.spacing_mm)

    with tempfile.TemporaryDirectory() as tmp:
        for case in cases(Path(tmp)):
            rows.append((case, measure(case)))
            print(f"{case.name}: " + "; ".join(error_cell(c) for c in rows[-1][1])
                  + f" ({(time.perf_counter() - t0) / 60:.1f} min)", file=sys.stderr, flush=True)
    return args, rows


def case_table(columns: list[str], rows: list[tuple[BenchCase, list]]) -> list[str]:
    """Markdown lines of a per-case table: a header with ``columns``, then one row of :func:`error_cell`
    cells per case."""
    return (["| case | " + " | ".join(columns) + " |", "|---|" + "---:|" * len(columns)]
            + [f"| {case.name} | " + " | ".join(error_cell(c) for c in cells) + " |" for case, cells in rows])


def case_groups(rows: list[tuple[BenchCase, list]]) -> dict[str, list[list]]:
    """The rows' cells by kind of case: plain real heads, real heads with arteries, phantoms (empty kinds left out)."""
    phantom = lambda case: case.name.startswith("phantom")  # noqa: E731
    groups = {
        "plain real heads": [cells for case, cells in rows if case.carotid_points_mm is None],
        "real heads with arteries": [cells for case, cells in rows if case.carotid_points_mm is not None and not phantom(case)],
        "phantoms": [cells for case, cells in rows if phantom(case)],
    }
    return {name: picked for name, picked in groups.items() if picked}


def publish(table: str, doc: Path | None, title: str, intro: str) -> None:
    """Print ``table``; with ``doc``, write it there under ``# title`` and ``intro``."""
    print(table)
    if doc:
        doc.write_text(f"# {title}\n\n{intro}\n\n{table}\n")
