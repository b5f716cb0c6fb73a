"""``geopose bench``: the paper's tables on held-out phantom subjects (and real head CTs, also
given a phantom's arteries with ``--real-arteries``).

Writes ``OUT/bench.md``, ``OUT/bench.json`` and ``OUT/tto_convergence.png``; each
case's results are kept in ``OUT/cases/`` so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from .. import __version__
from ..errors import InputError
from ..register.cli import options_from_args, registration_option_args
from ..register.engine import resolve_engine
from ..resources import default_models_dir
from .cases import ARTERIES_SUFFIX, ge_head_case, headsq_case, phantom_case, training_seeds
from .report import convergence_figure, markdown, summarise
from .run import (DRIFT_ROW, INSTANT_ROW, LEARNED_ROW, MIRRORED_SUFFIX, NATIVE_TTO_ROW, BenchSettings, crossed_name,
                  evaluate_case, evaluate_crossed, evaluate_mirrored, row_names)

#: First held-out phantom seed (training populations use small seeds; checked at run time).
DEFAULT_SEED_START = 5000

#: Case-name suffix of subjects run without the long TTO budget.
SHORT_CASE_SUFFIX = "-short"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark the method on held-out phantom subjects (paper table shape)")
    p.add_argument("--subjects", type=int, default=40, help="number of held-out phantom subjects")
    p.add_argument("--out", required=True, help="output folder (bench.md, bench.json, tto_convergence.png)")
    p.add_argument("--seed-start", type=int, default=DEFAULT_SEED_START, help="first phantom seed")
    p.add_argument("--long-subjects", type=int, help="subjects that also get the long native TTO (default: all)")
    p.add_argument("--long-iterations", type=int, default=400, help="long native TTO budget (0: skip)")
    p.add_argument("--spacing-mm", type=float, default=1.0, help="phantom voxel size (mm)")
    p.add_argument("--headsq", help="the real head CT headsq (quarter_sidecar.mhd) for real-anatomy rows")
    p.add_argument("--ge-head", help="the real GE head CT (its DICOM series folder) for real-anatomy rows")
    p.add_argument("--real-seeds", type=int, default=3, help="simulated run pairs per real head")
    p.add_argument("--real-arteries", action="store_true",
                   help="also run each real head made a CTA with a phantom's arteries (cases NAME+arteries-SEED)")
    p.add_argument("--dense", nargs="*", default=[], metavar="INJECTION",
                   help="also run the first --dense-subjects held-out phantoms with each of these injections (densely "
                        "opacified runs, e.g. all territories), reported in their own section")
    p.add_argument("--dense-subjects", type=int, default=5, help="held-out phantoms per --dense injection")
    p.add_argument("--mirrored-subjects", type=int, default=0,
                   help="held-out phantoms also registered with their CTA mirrored left-right (the mirror test must fail them)")
    p.add_argument("--crossed-subjects", type=int, default=0,
                   help="wrong pairings: the CTAs of this many held-out phantoms each registered with the next subject's "
                        "runs (the registration must fail them)")
    p.add_argument("--native-runs", action="store_true",
                   help="write the phantoms' runs archived native (unsubtracted, with the Mask Subtraction Sequence that "
                   "subtracts them), as many angiography systems store DSA; the registration reads them subtracted")
    p.add_argument("--models", help="model folder with its manifest.json (default: the shipped models)")
    p.add_argument("--allow-unverified-models", action="store_true",
                   help="use a --models folder without manifest.json (its files are not checksum-verified)")
    registration_option_args(p)
    p.set_defaults(func=run)


def _load_or_run(path: Path, compute) -> dict:
    if path.is_file():
        return json.loads(path.read_text())
    result = compute()
    path.write_text(json.dumps(result))
    return result


def run(args: argparse.Namespace) -> int:
    if args.subjects < 1:
        raise InputError(f"--subjects must be at least 1, got {args.subjects}")
    if not 0 <= args.mirrored_subjects <= args.subjects:
        raise InputError(f"--mirrored-subjects must lie between 0 and --subjects ({args.subjects}), got {args.mirrored_subjects}")
    if not 0 <= args.crossed_subjects < args.subjects:
        raise InputError(f"--crossed-subjects must lie between 0 and --subjects - 1 ({args.subjects - 1}): each CTA is "
                         f"paired with the next subject's runs; got {args.crossed_subjects}")
    out = Path(args.out)
    (out / "cases").mkdir(parents=True, exist_ok=True)
    models_dir = Path(args.models) if args.models else default_models_dir()
    seeds = list(range(args.seed_start, args.seed_start + args.subjects))
    manifest = models_dir / "manifest.json"
    if manifest.is_file():
        overlap = sorted(set(seeds) & training_seeds(manifest))
        if overlap:
            raise InputError(f"seeds {overlap[:5]} were used to train these models: choose --seed-start beyond them")
    options = options_from_args(args)
    backend, device, models = resolve_engine(options, models_dir, allow_unverified=args.allow_unverified_models)
    settings = BenchSettings(options, args.long_iterations)
    n = options.tto.iterations
    n_long = args.subjects if args.long_subjects is None else args.long_subjects
    cases: list[dict] = []
    mirrored: list[dict] = []
    crossed: list[dict] = []
    previous = None
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i, seed in enumerate(seeds):
            long = i < n_long
            tag = f"phantom-{seed}{'' if long else SHORT_CASE_SUFFIX}"
            case = functools.cache(lambda seed=seed: phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm,
                                                                  native_runs=args.native_runs))
            result = _load_or_run(out / "cases" / f"{tag}.json", lambda: evaluate_case(case(), models, settings, long=long))
            cases.append(result)
            if i < args.mirrored_subjects:
                mirrored.append(_load_or_run(out / "cases" / f"phantom-{seed}{MIRRORED_SUFFIX}.json",
                                             lambda: evaluate_mirrored(case(), models, settings)))
            if 0 < i <= args.crossed_subjects:
                name = crossed_name(f"phantom-{seeds[i - 1]}", f"phantom-{seed}")
                crossed.append(_load_or_run(out / "cases" / f"{name}.json",
                                            lambda: evaluate_crossed(previous(), case(), models, settings)))
            previous = case
            elapsed = time.perf_counter() - t_start
            row = LEARNED_ROW.format(n=n) if n > 0 else INSTANT_ROW
            mpcd = [result["rows"][row][v].get("mpcd_mm") for v in ("pa", "lat")]
            print(f"[{i + 1}/{len(seeds)}] {tag}: {row} mPCD PA {mpcd[0]:.2f} / LAT {mpcd[1]:.2f} mm; "
                  f"elapsed {elapsed / 60:.1f} min", flush=True)
        dense = []
        for injection in args.dense:
            for seed in seeds[: args.dense_subjects]:
                tag = f"phantom-{seed}-{injection}"
                dense.append(_load_or_run(out / "cases" / f"{tag}.json", lambda: evaluate_case(
                    phantom_case(seed, Path(tmp) / tag, args.spacing_mm, injection, args.native_runs), models, settings,
                    long=False)))
                print(f"dense {tag} done; elapsed {(time.perf_counter() - t_start) / 60:.1f} min", flush=True)
        real = []
        variants = (False, True) if args.real_arteries else (False,)
        for name, source, make in (("headsq", args.headsq, headsq_case), ("ge-head", args.ge_head, ge_head_case)):
            for arteries in variants:
                for seed in range(args.real_seeds if source else 0):
                    tag = f"{name}{ARTERIES_SUFFIX if arteries else ''}-{seed}"
                    real.append(_load_or_run(out / "cases" / f"{tag}.json", lambda: evaluate_case(
                        make(source, seed, arteries=arteries), models, settings, long=False)))
                    print(f"real head {tag} done; elapsed {(time.perf_counter() - t_start) / 60:.1f} min", flush=True)
    summary = summarise(cases, n)
    case_devices = sorted({str(c.get("device", device)) for c in cases + dense + real})
    ran_on = "" if case_devices == [str(device)] else f"; the cases (resumed from {out / 'cases'}) ran on {', '.join(case_devices)}"
    long_note = f"long native TTO on {min(n_long, len(cases))} subjects" if args.long_iterations > 0 else "no long native TTO"
    header = (
        f"# GeoPose benchmark on {len(cases)} held-out phantom subjects\n\n"
        f"Seeds {seeds[0]}..{seeds[-1]} (disjoint from the training seeds), {args.spacing_mm:g} mm phantoms"
        f"{' with runs archived native (read subtracted by their Mask Subtraction Sequence)' if args.native_runs else ''}, "
        f"models `{models_dir.name}` ({backend}), device `{device}` ({platform.machine()}, "
        f"{os.cpu_count()} CPUs){ran_on}, geopose {__version__}; "
        f"{long_note}.\n\n"
        f"Reproduce: `geopose bench --subjects {args.subjects} --seed-start {args.seed_start} --long-subjects {n_long} "
        f"--long-iterations {args.long_iterations} --spacing-mm {args.spacing_mm:g} "
        f"{'--native-runs ' if args.native_runs else ''}--out {out}{' --headsq ' + args.headsq if args.headsq else ''}{' --ge-head ' + args.ge_head if args.ge_head else ''}"
        f"{' --real-seeds ' + str(args.real_seeds) if real else ''}"
        f"{' --real-arteries' if args.real_arteries else ''}"
        f"{' --dense ' + ' '.join(args.dense) + f' --dense-subjects {args.dense_subjects}' if args.dense else ''}"
        f"{f' --mirrored-subjects {args.mirrored_subjects}' if mirrored else ''}"
        f"{f' --crossed-subjects {args.crossed_subjects}' if crossed else ''}`"
    )
    (out / "bench.md").write_text(markdown(summary, header, real, n, dense, mirrored, crossed))
    (out / "bench.json").write_text(json.dumps(_rounded({"summary": summary, "cases": cases, "real_heads": real,
                                                         "dense": dense, "mirrored": mirrored, "crossed": crossed}),
                                               separators=(",", ":")))
    curve_rows = [r for r in row_names(settings) if r in (LEARNED_ROW.format(n=n), NATIVE_TTO_ROW.format(n=n), DRIFT_ROW.format(n=n))
                  or r.startswith("DICOM angles + ") and r != NATIVE_TTO_ROW.format(n=n)]
    convergence_figure(cases, curve_rows, out / "tto_convergence.png")
    print((out / "bench.md").read_text())
    return 0


#: Significant digits of the numbers in ``bench.json`` (the committed file stays small in git's history).
JSON_DIGITS = 5


def _rounded(value):
    """``value`` with every float rounded to :data:`JSON_DIGITS` significant digits."""
    if isinstance(value, float):
        return float(f"{value:.{JSON_DIGITS}g}")
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    return value
