"""Run the GeoPose input fuzz suite and print (optionally write) the outcome table.

    python Testing/fuzz/run.py --cases 10000 --cli-cases 1000 --seed 0 --workers 2 --doc docs/fuzz.md

runs the reader cases (mutated files, ``targets.py``), then the CLI-level cases (``geopose register``
situations, ``cli_targets.py``)
(``make fuzz`` runs this with ``nice -n 10``). Exit code 1 when any case failed
(accepted WRONG, other exception, out of memory, hang, crash).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
try:
    import geopose  # noqa: F401
except ImportError:
    sys.path.insert(0, str(HERE.parents[1] / "Logic"))

import harness  # noqa: E402
import targets  # noqa: E402
import cli_targets  # noqa: E402


def fuzz(cases: int, seed: int, workers: int, timeout_s: float, memory_bytes: int, first: int = 0,
         progress: bool = False, suite: str = "readers") -> harness.Report:
    """Build the originals in a temporary folder and run cases ``first .. first + cases - 1`` of ``suite``:
    ``readers`` (mutated files, :mod:`targets`) or ``cli`` (``geopose register`` situations, :mod:`cli_targets`)."""
    with tempfile.TemporaryDirectory(prefix="geopose-fuzz-") as tmp:
        root = Path(tmp) / "originals"
        if suite == "cli":
            cli_targets.build_cli_originals(root)
        else:
            originals = targets.build_originals(root)
        work = Path(tmp) / "work"

        def case(index: int) -> tuple[str, str, str, str]:
            if not getattr(case, "quiet", False):  # once per worker: keep C++ readers' messages off the console
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, 2)
                warnings.simplefilter("ignore")
                case.quiet = True  # type: ignore[attr-defined]
            scratch = Path(harness.pid_scratch(str(work)))
            if suite == "cli":
                return cli_targets.run_cli_case(seed, index, root, scratch)
            return targets.run_case(seed, index, root, originals, scratch)

        step = max(1, cases // 20)

        def report_progress(done: int) -> None:
            if progress and (done % step == 0 or done == cases):
                print(f"  {suite}: {done}/{cases} cases", file=sys.stderr, flush=True)

        describe = cli_targets.describe_cli_case if suite == "cli" else targets.describe_case
        return harness.run_cases(
            case, range(first, first + cases), describe=lambda i: describe(seed, i), workers=workers,
            timeout_s=timeout_s, memory_bytes=memory_bytes, progress=report_progress,
        )


def _faithful_table(report: harness.Report) -> str:
    kinds = ("flip", "flip_header", "truncate", "field")
    counts: dict[str, dict[str, int]] = {}
    for r in report.results:
        if r.outcome == "accepted, faithful":
            row = counts.setdefault(r.target, dict.fromkeys(kinds, 0))
            row[r.mutation.split(":")[0]] += 1
    lines = ["| target | " + " | ".join(kinds) + " |", "|---|" + "---:|" * len(kinds)]
    lines += [f"| {t} | " + " | ".join(str(counts[t][k]) for k in kinds) + " |" for t in sorted(counts)]
    return "\n".join(lines)


def document(report: harness.Report, seconds: float, command: str) -> str:
    failures = report.failures()
    lines = [
        "# Input fuzz suite",
        "",
        "Every GeoPose input reader, fed seeded mutations of valid files: bit flips anywhere or in the header, "
        "truncation, and header fields set to damaging values (sizes, bit depths, transfer syntax, angles, distances, "
        "spacings, element lengths, deleted tags; a native run's Mask Subtraction Sequence: operation, mask frames, "
        "frame range, sub-pixel shift, contrast averaging, intensity relationship and its sign, the sequence deleted; "
        "NIfTI/NRRD/MetaImage header fields; JSON values of the wrong type, "
        "deep nesting; manifest entries as lists, without sizes, pointing outside the folder). Each case runs in a "
        "forked worker with a memory limit and a timeout (`Testing/fuzz/harness.py`); the targets and the verification "
        "are in `Testing/fuzz/targets.py`.",
        "",
        f"Command: `{command}`  ",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; {seconds / 60:.1f} min.",
        "",
        report.table(),
        "",
        "Outcomes: **clean error**: one `InputError` line naming the file, the problem and the remedy. "
        "**accepted, identical**: the same image and geometry as the original (e.g. a flipped bit in an unused "
        "header byte, or in bits the format ignores). **accepted, faithful**: different from the original, and "
        "exactly what an independent reader (pydicom's own decoders and tags, SimpleITK, `json`) finds in the "
        "mutated file: the mutation changed a value no format check can tell from a real one (a pixel or voxel "
        "value, a digit of an angle or spacing, a JPEG entropy-coded bit that still decodes; DICOM, NIfTI, NRRD "
        "and MetaImage carry no checksum of their data). For a CT series whose slice geometry the mutation "
        "changed, faithful means the reader noticed and resampled. JPEG 2000 Lossless streams written by "
        "OpenJPEG are re-encoded and compared, so only flips that re-encode to themselves pass. "
        "**accepted, WRONG**, **other exception** (a traceback), **out of memory**, **hang** and **crash** are "
        "failures.",
        "",
        "Accepted, faithful cases by mutation kind (`flip`: anywhere, mostly pixel/voxel data; `flip_header`: "
        "in the header; `field`: a header value set on purpose, e.g. another angle):",
        "",
        _faithful_table(report),
        "",
        f"Failures: {len(failures)}.",
    ]
    for r in failures[:30]:
        lines.append(f"- case {r.index} ({r.target}, {r.mutation}): {r.outcome}: {r.detail.splitlines()[-1] if r.detail else ''}")
    return "\n".join(lines) + "\n"


def document_cli(report: harness.Report, seconds: float) -> str:
    """The CLI-level section of docs/fuzz.md."""
    situations: dict[str, dict[str, int]] = {}
    for r in report.results:
        if r.target.startswith("ct_"):
            kind = ", ".join(r.mutation.split(", ")[:2])
        else:
            kind = r.mutation.split(" (")[0].split(" as ")[0]
        kind = kind or "(no detail: the case did not finish)"
        row = situations.setdefault(f"{r.target}: {kind}", {})
        row[r.outcome] = row.get(r.outcome, 0) + 1
    lines = [
        "",
        "## CLI level: `geopose register` as a user runs it",
        "",
        "Each case arranges one situation in a fresh folder and runs the real entry point (`geopose.cli.main`) in the "
        f"forked worker ({seconds / 60:.1f} min; `Testing/fuzz/cli_targets.py`): an `--out` that is, contains or links to an "
        "input (inputs renamed to the output names inside it, the inputs' folder, an ancestor, an input file, a DICOM series "
        "folder, `/`); a device, FIFO, socket or symlink (chain) to `/dev/zero` as the CTA, a run, a slice of a series, a "
        "frame of a run folder or a sidecar; a run or a CTA series of another patient, a run of another study, one run for "
        "both views (same path, same bytes, same DICOM instance). A **clean error** here is exit code 2 with one "
        "`geopose register: error:` line that names the situation, every input byte-identical afterwards (SHA-256 of every "
        "file before and after) and nothing written into an input's folder. `ct_encoding`: a signed CT series "
        "(uncompressed, JPEG Lossless SV1, JPEG-LS, JPEG 2000, RLE; BitsStored 16 or 12; a random PixelPaddingValue) read by "
        "`load_cta`, **accepted, faithful** when every voxel inside the scan circle equals pydicom's `pixel_array` and "
        "SimpleITK/GDCM's series read (which agree) and the padding reads as air. `ct_misdeclared`: the same with "
        "PixelRepresentation 0 (signed data declared unsigned) through the CLI: refused by the HU or BitsStored check, "
        "or, where the unsigned reading is plausible CT (a 12-bit two's complement pattern can be), read exactly as "
        "pydicom reads the header as it stands (faithful; no registration is run).",
        "",
        report.table(),
        "",
        "| situation | " + " | ".join(harness.OUTCOMES[:4]) + " | failures |",
        "|---|" + "---:|" * 5,
    ]
    for name in sorted(situations):
        row = situations[name]
        lines.append(f"| {name} | " + " | ".join(str(row.get(o, 0)) for o in harness.OUTCOMES[:4])
                     + f" | {sum(row.get(o, 0) for o in harness.FAILURES)} |")
    failures = report.failures()
    lines += ["", f"Failures: {len(failures)}."]
    for r in failures[:30]:
        lines.append(f"- case {r.index} ({r.target}, {r.mutation}): {r.outcome}: {r.detail.splitlines()[-1] if r.detail else ''}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--first", type=int, default=0, help="first case index (to re-run one case: --first N --cases 1)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timeout-s", type=float, default=30.0, help="per case")
    parser.add_argument("--memory-gb", type=float, default=2.0, help="per worker, beyond its size at start")
    parser.add_argument("--doc", type=Path, help="write the table and command to this Markdown file")
    parser.add_argument("--cli-cases", type=int, default=1000, help="CLI-level cases (geopose register), after the reader cases")
    parser.add_argument("--verbose", action="store_true", help="print every case")
    args = parser.parse_args(argv)
    reports, failures = {}, []
    for suite, cases in (("readers", args.cases), ("cli", args.cli_cases)):
        if cases <= 0:
            continue
        start = time.perf_counter()
        report = fuzz(cases, args.seed, args.workers, args.timeout_s, int(args.memory_gb * 2**30), args.first, progress=True,
                      suite=suite)
        seconds = time.perf_counter() - start
        reports[suite] = (report, seconds)
        if args.verbose:
            for r in report.results:
                print(f"{r.index}\t{r.target}\t{r.outcome}\t{r.mutation}\t{r.detail.splitlines()[-1] if r.detail else ''}")
        print(report.table())
        failures += report.failures()
        print(f"{suite}: {len(report.results)} cases in {seconds:.0f} s; {len(report.failures())} failures")
    for r in failures[:30]:
        print(f"  case {r.index} ({r.target}, {r.mutation}): {r.outcome}\n    {r.detail[-800:]}")
    if args.doc and "readers" in reports:
        command = (f"python Testing/fuzz/run.py --cases {args.cases} --cli-cases {args.cli_cases} --seed {args.seed} "
                   f"--workers {args.workers} --timeout-s {args.timeout_s:g} --memory-gb {args.memory_gb:g}"
                   + (f" --first {args.first}" if args.first else ""))
        text = document(*reports["readers"], command=command)
        if "cli" in reports:
            text += document_cli(*reports["cli"])
        args.doc.write_text(text)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
