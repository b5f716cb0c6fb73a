"""``geopose demo``: a phantom case registered end to end with the shipped models.

Writes the phantom (CTA, labels, centrelines, truth, two DSA runs) into
``OUT/case``, registers it, and leaves ``result.json`` and overlay PNGs in ``OUT``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .cta import load_cta, save_volume
from .phantom.cli import write_phantom
from .phantom.labels import vessel_mask
from .register.cli import print_summary, register_files
from .options import BACKENDS, RegistrationOptions, TTOSchedule

DEMO_SEED = 20260


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="register a phantom case end to end (writes pictures and result.json)")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--seed", type=int, default=DEMO_SEED, help="phantom subject seed")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--iterations", type=int, default=TTOSchedule.iterations, help="test-time optimisation steps")
    p.add_argument("--backend", choices=BACKENDS, default="auto", help="auto, torch or onnxruntime")
    p.set_defaults(func=run)


def write_demo_case(case: Path, seed: int = DEMO_SEED, spacing_mm: float = 1.0) -> dict:
    """The demo's phantom subject in ``case`` (``geopose phantom``'s files) plus ``vessels.nii.gz``,
    its arteries as the vessel label map (a user's segmentation, as the browser app's demo case reads it;
    ``geopose demo`` registers without it); returns the phantom's timings (s)."""
    timings = write_phantom(seed, case, spacing_mm=spacing_mm)
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    save_volume(labels.like(vessel_mask(labels.array).astype("uint8")), case / "vessels.nii.gz")
    return timings


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    case = out.with_name(out.name + "_case")  # beside the results: an --out folder may hold no input
    print(f"[1/2] generating phantom subject {args.seed} in {case}")
    timings = write_phantom(args.seed, case)
    print("      " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    print("[2/2] registering the CTA to the PA + lateral DSA pair as a user would: the CTA and the two runs only "
          "(masks computed from them; the phantom's labels and truth serve only to score the result)")
    record = register_files(
        case / "cta.nii.gz", case / "dsa_pa.dcm", case / "dsa_lat.dcm", out,
        options=RegistrationOptions(device=args.device, backend=args.backend).replace(**{"tto.iterations": args.iterations}),
    )
    print_summary(record, out)
    return 0
