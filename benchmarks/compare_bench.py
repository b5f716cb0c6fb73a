"""Paired comparison of two `geopose bench` outputs on the subjects they share: per row,
the mean and median carotid mPCD (PA and LAT averaged within each subject), the success
rate over views and the mean rotation and translation errors. Prints a Markdown table;
``--doc`` writes it.

    .venv/bin/python benchmarks/compare_bench.py docs/benchmark /tmp/clip_a /tmp/clip_b \\
        --labels "25-75 (docs/conventions.md 5)" "2-98" --doc docs/benchmark/model_clip.md
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Logic"))

from geopose.bench import BenchSettings, row_names  # noqa: E402
from geopose.bench.cli import SHORT_CASE_SUFFIX  # noqa: E402
from geopose.register.case import VIEW_KEYS as VIEWS  # noqa: E402

#: The rows compared: the paper's table without the native start and the long TTO budget.
ROWS = tuple(r for r in row_names(BenchSettings(), long=False) if r != "native")


def load_cases(folders: list[Path]) -> dict[str, dict]:
    """Case records of one configuration, by subject (``phantom-5000``), from its
    ``bench.json`` or, for a run in progress, its ``cases/`` folder."""
    cases: dict[str, dict] = {}
    for folder in folders:
        summary = folder / "bench.json"
        found = json.loads(summary.read_text())["cases"] if summary.is_file() else [
            json.loads(p.read_text()) for p in sorted((folder / "cases").glob("phantom-*.json"))]
        cases.update({c["case"].removesuffix(SHORT_CASE_SUFFIX): c for c in found})
    return cases


def row_stats(cases: dict[str, dict], names: list[str], row: str) -> tuple[float, float, float, float, float]:
    """(mean mPCD, median mPCD, success %, mean rotation deg, mean translation mm)."""
    per_subject = [statistics.mean(cases[n]["rows"][row][v]["mpcd_mm"] for v in VIEWS) for n in names]
    views = [cases[n]["rows"][row][v] for n in names for v in VIEWS]
    return (statistics.mean(per_subject), statistics.median(per_subject),
            100.0 * sum(v["success"] for v in views) / len(views),
            statistics.mean(v["rotation_error_deg"] for v in views),
            statistics.mean(v["translation_error_norm_mm"] for v in views))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", type=Path, help="bench output folder of the reference configuration")
    ap.add_argument("other", type=Path, nargs="+", help="bench output folder(s) of the other configuration")
    ap.add_argument("--labels", nargs=2, default=("base", "other"))
    ap.add_argument("--doc", type=Path, default=None)
    args = ap.parse_args()
    base, other = load_cases([args.base]), load_cases(args.other)
    names = sorted(set(base) & set(other))
    if not names:
        raise SystemExit("the two configurations share no subject: point at bench output folders of the same seeds")
    a, b = args.labels
    head = ["mPCD mean (mm)", "mPCD median (mm)", "success", "rot. err. (deg)", "transl. err. (mm)"]
    lines = [
        f"{len(names)} subjects ({names[0]} .. {names[-1]}), {2 * len(names)} views; each cell: {a} -> {b}.",
        "",
        "| row | " + " | ".join(head) + " |",
        "|---|" + "---:|" * len(head),
    ]
    for row in ROWS:
        if not all(row in base[n]["rows"] and row in other[n]["rows"] for n in names):
            continue
        x, y = row_stats(base, names, row), row_stats(other, names, row)
        cells = [f"{x[i]:.1f} -> {y[i]:.1f}" if i != 2 else f"{x[i]:.0f} % -> {y[i]:.0f} %" for i in range(len(head))]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    right = [other[n]["views"][v]["init_view"] == other[n]["views"][v]["true_view"] for n in names for v in VIEWS]
    lines += ["", f"View accuracy ({b}): {sum(right)}/{len(right)}."]
    table = "\n".join(lines)
    print(table)
    if args.doc:
        args.doc.write_text(f"# Benchmark comparison: {a} vs {b}\n\n`benchmarks/compare_bench.py`\n\n{table}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
