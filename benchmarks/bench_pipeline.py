"""Time the registration on a laptop-class CPU: per stage, per engine, at the CTA resolutions
clinical scans come in, with peak memory, and under load.

Every row runs the path a user takes: ``register_case`` with the CTA and the two runs, the masks computed.
Rows (each a fresh process, so peak memory is that run's):
* ``torch`` and ``onnxruntime`` engines on the 1 mm 256^3 demo phantom, every option at its
  default (25 TTO steps; the onnxruntime engine runs its TTO in torch);
* the torch-free path (onnxruntime + numpy in a process where PyTorch cannot be imported;
  the TTO is skipped);
* the same phantom's CTA resampled to 0.5 mm (512^3, what clinical CTAs are);
* the torch engine while two other processes keep both cores busy, with OpenMP's wait
  policy PASSIVE (the library's default) and ACTIVE (spinning threads).

The stage table, the instant result (calibration + Init + greedy Refine + the similarity search), the time from the
start at which the networks' estimate is handed to the front end (``register_case``'s ``preliminary``: what the Slicer
panel shows while the TTO runs) and peak RSS go to
``--doc`` (Markdown) and a JSON beside it.

    .venv/bin/python benchmarks/bench_pipeline.py --threads 2 --doc docs/pipeline_benchmark.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "Logic"))

from geopose.cta import load_cta, save_volume  # noqa: E402
from geopose.phantom.cli import write_phantom  # noqa: E402
from geopose.volume import Volume  # noqa: E402

#: The paper's H100 runtimes (docs/conventions.md section 8), for comparison.
PAPER_S = {"calibration + init": 0.0218, "refine": 0.147, "tto": 2.0}
STAGES = ("prepare", "calibration", "init", "refine", "search", "tto", "mirror", "pairing", "score", "total")
MARKER = "<!-- bench:pipeline -->"

_BLOCK_TORCH = """
import sys
class _NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("PyTorch is blocked in this benchmark process")
        return None
sys.meta_path.insert(0, _NoTorch())
"""

_RUN = """
import json, sys, time
folder, backend, iterations, threads = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
try:
    import torch
    torch.set_num_threads(threads)
except ImportError:
    pass
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.options import RegistrationOptions, TTOSchedule
from geopose.register import register_case
t0 = time.perf_counter()
cta = load_cta(f"{folder}/cta.nii.gz")
runs = {k: read_dsa(f"{folder}/dsa_{k}.dcm") for k in ("pa", "lat")}
read_s = time.perf_counter() - t0
def peak_rss_gb():
    # VmHWM: this process's own peak (ru_maxrss would include the parent's peak from before exec)
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1e6
rss_before = peak_rss_gb()
shown = []
result = register_case(cta, runs, options=RegistrationOptions(backend=backend, tto=TTOSchedule(iterations=iterations)),
                       preliminary=lambda p: shown.append(p.elapsed_s))
out = dict(result.runtimes_s, read=read_s, peak_rss_gb=peak_rss_gb(), estimate_shown_s=shown[0],
           rss_after_reading_gb=rss_before, engine=result.engine, notes=result.notes,
           poses={k: v.final_pose.tolist() for k, v in result.views.items()})
print("RESULT " + json.dumps(out))
"""


def _run(folder: Path, backend: str, iterations: int, threads: int, *, block_torch: bool = False,
         env: dict | None = None) -> dict:
    code = (_BLOCK_TORCH if block_torch else "") + textwrap.dedent(_RUN)
    proc = subprocess.run([sys.executable, "-c", code, str(folder), backend, str(iterations), str(threads)],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO / "Logic"), **(env or {})})
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-3000:])
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


def _upsample(folder: Path, out: Path) -> None:
    """The case with its CTA on a 0.5 mm grid: each voxel split in eight."""
    out.mkdir(parents=True, exist_ok=True)
    vol = load_cta(folder / "cta.nii.gz")
    fine = vol.array.repeat(2, 0).repeat(2, 1).repeat(2, 2)
    affine = vol.ijk_to_ras.copy()
    affine[:3, :3] /= 2.0
    affine[:3, 3] -= 0.25 * (vol.ijk_to_ras[:3, :3] @ [1.0, 1.0, 1.0])  # keep the grid's physical extent
    save_volume(Volume(fine, affine), out / "cta.nii.gz")
    for name in ("dsa_pa.dcm", "dsa_lat.dcm"):
        (out / name).symlink_to(folder / name)


def _busy(n: int) -> list[subprocess.Popen]:
    """``n`` processes that spin on a core each (the 'other work' of a laptop)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _table(rows: dict[str, dict]) -> str:
    head = ("| run | " + " | ".join(STAGES) + " | instant (cal + Init + greedy + search) | estimate shown (from the start) "
            "| peak RSS (GB) |")
    lines = [head, "|" + "---|" * (len(STAGES) + 4)]
    for name, r in rows.items():
        instant = r["calibration"] + r["init"] + r["refine"] + r.get("search", 0.0)
        cells = [f"{r[s]:.2f}" if s in r else "-" for s in STAGES]  # a stage that did not run: -
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {instant:.2f} | {r['estimate_shown_s']:.2f} "
                     f"| {r['peak_rss_gb']:.2f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=20260)
    ap.add_argument("--iterations", type=int, default=25)
    ap.add_argument("--repeats", type=int, default=2, help="runs per row (the best is reported)")
    ap.add_argument("--doc", type=Path)
    args = ap.parse_args()
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        case = Path(tmp) / "case"
        write_phantom(args.seed, case)
        fine = Path(tmp) / "fine"
        _upsample(case, fine)

        def best(**kw) -> dict:
            runs = [_run(**kw) for _ in range(args.repeats)]
            return min(runs, key=lambda r: r["total"])

        common = dict(iterations=args.iterations, threads=args.threads)
        rows["torch, 1 mm 256^3"] = best(folder=case, backend="torch", **common)
        rows["onnxruntime + numpy, 1 mm 256^3"] = best(folder=case, backend="onnxruntime", **common)
        rows["torch-free (no PyTorch: TTO skipped), 1 mm 256^3"] = best(folder=case, backend="auto", block_torch=True, **common)
        rows["torch, 0.5 mm 512^3"] = best(folder=fine, backend="torch", **common)
        rows["onnxruntime + numpy, 0.5 mm 512^3"] = best(folder=fine, backend="onnxruntime", **common)
        for policy in ("PASSIVE", "ACTIVE"):
            spinners = _busy(2)
            try:
                time.sleep(1.0)
                rows[f"torch, 1 mm, 2 busy processes, OMP_WAIT_POLICY={policy}"] = _run(
                    case, "torch", args.iterations, args.threads, env={"OMP_WAIT_POLICY": policy})
            finally:
                for p in spinners:
                    p.kill()
    header = (
        f"{platform.machine()}, {os.cpu_count()} CPUs, {args.threads} threads; phantom seed {args.seed}; shipped models; "
        f"{args.iterations} TTO steps; best of {args.repeats} (the busy-machine rows: one run each); 1-min load average "
        f"at the end {os.getloadavg()[0]:.2f}. Seconds per stage (`runtimes_s` of the result), reading the files excluded."
    )
    table = header + "\n\n" + _table(rows)
    print(table)
    if args.doc:
        text = args.doc.read_text() if args.doc.is_file() else "# Pipeline benchmark\n"
        if MARKER in text:
            before, rest = text.split(MARKER, 1)
            after = rest.split("<!-- end -->", 1)[1] if "<!-- end -->" in rest else ""
            text = before + MARKER + "\n" + table + "\n<!-- end -->" + after
        else:
            text += f"\n{MARKER}\n{table}\n<!-- end -->\n"
        args.doc.write_text(text)
        args.doc.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
