"""Benchmark our DRR renderer against DiffDRR 0.6.x on the same volume, pose and detector.

Times one image (batch 1) through a ``N^3`` synthetic head for each detector size:
*fwd* = render without autograd; *fwd+bwd* = render from Euler ZYX pose parameters
with autograd, loss = -NCC against a fixed target image, backward to the 6 pose
parameters. Reports the median of ``--repeats`` runs after ``--warmup`` runs, the
speed-up ratio DiffDRR time / our time, and the image NCC between each renderer and
DiffDRR's trilinear renderer (default sample count), so that speed is compared at
equal image quality. Without DiffDRR only our timings are printed.

Usage (from the repository root)::

    .venv-diffdrr/bin/python benchmarks/bench_renderer.py --threads 2 --device cpu --doc docs/renderer_benchmark.md
    python benchmarks/bench_renderer.py --device cuda --doc docs/renderer_benchmark.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import renderer_common as rc
from geopose.geometry import RigidTransform
from geopose.render import DRR
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

DEFAULT_STEPS_MM = (0.45, 0.9, 1.35)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_round_robin(fns: dict[str, Callable[[], None]], device: torch.device, warmup: int, repeats: int) -> dict[str, dict]:
    """Median and minimum wall time (s) of each function over ``repeats`` rounds after
    ``warmup`` rounds; the functions take turns within each round, so that a change in
    machine load affects all of them alike."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    _sync(device)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            _sync(device)
            t0 = time.perf_counter()
            fn()
            _sync(device)
            times[key].append(time.perf_counter() - t0)
    return {k: {"median": statistics.median(v), "min": min(v)} for k, v in times.items()}


def neg_ncc(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a = a.flatten()
    b = b.flatten()
    a = (a - a.mean()) / a.std()
    b = (b - b.mean()) / b.std()
    return -(a * b).mean()


class Case:
    """One renderer under test: ``render(r, t) -> (1, 1, H, W)`` from pose parameters."""

    def __init__(self, name: str, render: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]):
        self.name = name
        self.render = render


def ours_case(volume, detector, step_mm: float, device: torch.device) -> Case:
    drr = DRR.from_volume(volume, detector, device=device, step_mm=step_mm)

    def render(r: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return drr(RigidTransform.from_euler_zyx(r, t))[:, :1]

    return Case(f"ours trilinear step {step_mm:g} mm", render)


def diffdrr_cases(volume, detector, device: torch.device) -> list[Case]:
    cases = []
    for renderer in ("trilinear", "siddon"):
        adapter = rc.DiffDRRAdapter(volume, detector, renderer=renderer, device=device)
        label = f"DiffDRR trilinear ({rc.default_trilinear_samples()} samples)" if renderer == "trilinear" else "DiffDRR Siddon"
        cases.append(Case(label, adapter.render_params))
    return cases


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch sees no CUDA device: use --device cpu")
    torch.set_num_threads(args.threads)
    version = None if args.no_diffdrr else rc.diffdrr_version()
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}, DiffDRR {version or 'absent'}")
    t0 = time.perf_counter()
    volume = rc.head_phantom(args.volume_size)
    print(f"phantom {args.volume_size}^3 built in {time.perf_counter() - t0:.1f} s")
    _, poses = rc.validation_poses(n_random=1, seed=args.seed)
    r0, t0_ = (x.float().to(device) for x in poses[3:4].euler_zyx())  # a perturbed PA pose
    rows = []
    for size in args.sizes:
        detector = rc.model_detector(size)
        cases = [ours_case(volume, detector, s, device) for s in args.steps]
        if version is not None:
            cases += diffdrr_cases(volume, detector, device)
        with torch.no_grad():
            images = {c.name: c.render(r0, t0_)[0, 0].float().cpu() for c in cases}
        reference = next((c.name for c in cases if c.name.startswith("DiffDRR trilinear")), None)
        target = images[reference or cases[0].name].to(device)
        # The target is the image at a pose 0.05 rad / 5 mm away, so the loss has a real gradient.
        r_start = r0 + 0.05
        t_start = t0_ + 5.0
        fns = {}
        for case in cases:
            def fwd(case=case) -> None:
                with torch.no_grad():
                    case.render(r_start, t_start)

            def fwd_bwd(case=case) -> None:
                r = r_start.clone().requires_grad_(True)
                t = t_start.clone().requires_grad_(True)
                neg_ncc(case.render(r, t)[0, 0], target).backward()

            fns[(case.name, "fwd")] = fwd
            fns[(case.name, "fwd_bwd")] = fwd_bwd
        times = time_round_robin(fns, device, args.warmup, args.repeats)
        for case in cases:
            ref = images[reference] if reference else None
            row = {
                "size": size,
                "renderer": case.name,
                "fwd_s": times[(case.name, "fwd")]["median"],
                "fwd_bwd_s": times[(case.name, "fwd_bwd")]["median"],
                "fwd_min_s": times[(case.name, "fwd")]["min"],
                "fwd_bwd_min_s": times[(case.name, "fwd_bwd")]["min"],
                "ncc_vs_diffdrr_trilinear": rc.ncc(images[case.name], ref) if reference else None,
                "patch_ncc_vs_diffdrr_trilinear": rc.patch_ncc(images[case.name], ref) if reference else None,
            }
            rows.append(row)
            print(
                f"  {size}x{size} {case.name:38s} fwd {row['fwd_s']*1e3:9.1f} ms (min {row['fwd_min_s']*1e3:9.1f})"
                f"  fwd+bwd {row['fwd_bwd_s']*1e3:9.1f} ms (min {row['fwd_bwd_min_s']*1e3:9.1f})"
            )
    return {
        "torch": torch.__version__,
        "diffdrr": version,
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or platform.machine(),
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average_1_5_15": list(os.getloadavg()),
        "volume": f"synthetic head {args.volume_size}^3, 0.9 mm voxels",
        "warmup": args.warmup,
        "repeats": args.repeats,
        "rows": rows,
    }


def markdown(result: dict) -> str:
    """Markdown table: per size and renderer, median times and DiffDRR/ours ratios."""
    lines = [
        f"Device `{result['device']}` ({result['device_name']}), torch {result['torch']}, "
        f"{result['threads']} threads, DiffDRR {result['diffdrr'] or 'absent'}; {result['volume']}; "
        f"median of {result['repeats']} after {result['warmup']} warm-up; 1-min load average at the end "
        f"{result['load_average_1_5_15'][0]:.2f} on {result['cpu_count']} CPUs.",
        "",
        "| detector | renderer | fwd ms | fwd+bwd ms | NCC vs DiffDRR tri | patch NCC vs DiffDRR tri "
        "| fwd speed-up vs DiffDRR tri / Siddon | fwd+bwd speed-up vs DiffDRR tri / Siddon |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for size in sorted({r["size"] for r in result["rows"]}):
        rows = [r for r in result["rows"] if r["size"] == size]
        tri = next((r for r in rows if r["renderer"].startswith("DiffDRR trilinear")), None)
        sid = next((r for r in rows if r["renderer"] == "DiffDRR Siddon"), None)
        for r in rows:
            def ratio(key: str) -> str:
                if tri is None or sid is None or r["renderer"].startswith("DiffDRR"):
                    return "-"
                return f"{tri[key] / r[key]:.1f}x / {sid[key] / r[key]:.1f}x"

            q = "-" if r["ncc_vs_diffdrr_trilinear"] is None else f"{r['ncc_vs_diffdrr_trilinear']:.5f}"
            pq = "-" if r["patch_ncc_vs_diffdrr_trilinear"] is None else f"{r['patch_ncc_vs_diffdrr_trilinear']:.4f}"
            lines.append(
                f"| {size}x{size} | {r['renderer']} | {r['fwd_s'] * 1e3:.1f} | {r['fwd_bwd_s'] * 1e3:.1f} | {q} | {pq} "
                f"| {ratio('fwd_s')} | {ratio('fwd_bwd_s')} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--sizes", type=int, nargs="+", default=[128, 256], help="detector sizes in px")
    p.add_argument("--volume-size", type=int, default=256, help="phantom grid size N (N^3 voxels)")
    p.add_argument("--steps", type=float, nargs="+", default=list(DEFAULT_STEPS_MM), help="our step_mm values")
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbed PA pose")
    p.add_argument("--no-diffdrr", action="store_true", help="time ours only even if DiffDRR is importable")
    p.add_argument(
        "--doc",
        type=Path,
        default=None,
        help="Markdown file whose section between <!-- bench:DEVICE --> and <!-- /bench:DEVICE --> "
        "is replaced by the table (appended if absent); the JSON goes beside it as <stem>_DEVICE.json",
    )
    args = p.parse_args(argv)
    result = run(args)
    table = markdown(result)
    print()
    print(table)
    if args.doc is not None:
        key = torch.device(args.device).type
        update_doc(args.doc, f"bench:{key}", table)
        js = args.doc.with_name(f"{args.doc.stem}_{key}.json")
        js.write_text(json.dumps(result, indent=2) + "\n")
        print(f"updated {args.doc} and wrote {js}")


def update_doc(path: Path, key: str, table: str) -> None:
    """Replace the text between ``<!-- key -->`` and ``<!-- /key -->`` in ``path``
    by ``table``, or append a new marked section."""
    start, end = f"<!-- {key} -->", f"<!-- /{key} -->"
    text = path.read_text() if path.exists() else ""
    block = f"{start}\n{table}{end}"
    if start in text and end in text:
        text = text[: text.index(start)] + block + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)

if __name__ == "__main__":
    main()
