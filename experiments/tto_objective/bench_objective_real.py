"""Where the TTO objective's optimum lies on real heads, and what puts it there: the TTO
started at the true pose of real head CTs with simulated runs (``geopose.bench.cases``), once
against the runs' own images and once with each of them replaced by its noise-free
counterpart, the DRR at the true pose sent through the same intensity chain:

* silhouette: the DRR's total channel clipped like the MAP (``objective.clip_like_target``
  over the DSA mask's columns) instead of the preprocessed MAP;
* vessels: the DRR of the vessels the runs show opacified (``opacified.read_opacified`` at the
  truth), min-max, instead of the vessel image made from the runs' frames.

A target that leaves the TTO at the truth holds no bias; the change the swap makes names the
image whose texture moves the optimum. ``--no-motion`` simulates the runs without patient
motion (no subtraction residue), ``--no-noise`` without quantum noise, to test either as the cause.

    .venv/bin/python experiments/tto_objective/bench_objective_real.py --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --seeds 0-2 --doc experiments/tto_objective/objective_real_heads.md
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))

import geopose.phantom.dsa as phantom_dsa  # noqa: E402
from geopose import contract as C  # noqa: E402
from geopose.bench.cases import BenchCase, ge_head_case, headsq_case, seed_range  # noqa: E402
from geopose.register.biplane import nominal_poses  # noqa: E402
from geopose.register.case import VIEW_KEYS, prepare_case  # noqa: E402
from geopose.register.evaluate import evaluate_pose  # noqa: E402
from geopose.register.objective import clip_like_target  # noqa: E402
from geopose.register.opacified import read_opacified  # noqa: E402
from geopose.register.tto import tto_views  # noqa: E402
from geopose.register.tto import TTOSchedule, TTOView, test_time_optimise  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

#: Columns of the table: which target images are the runs' own and which the noise-free DRR's.
VARIANTS = ("the runs' images (default)", "noise-free silhouette", "noise-free vessels", "both noise-free")


def _noise_free(views: list[TTOView], renderer: TorchRenderer, rig: dict, X: np.ndarray,
                silhouette: bool, vessels: bool) -> list[TTOView] | None:
    """``views`` with the silhouette target and/or the vessel image replaced by the DRR's at their
    (true) poses; None when vessels are asked for and the case has none opacified."""
    out = list(views)
    if silhouette:
        out = [replace(v, target=clip_like_target(renderer.render(v.pose, v.detector, ("total",))[0], v.mask,
                                                  C.MAP_CLIP_PERCENTILES).astype(np.float32)) for v in out]
    if vessels:
        selection = read_opacified(renderer.volume, X, rig, [(v.name, v.vessels, v.detector) for v in views])
        if selection is None or not selection.applied:
            return None
        shown = TorchRenderer(selection.volume)
        images = {v.name: shown.render(v.pose, v.detector, ("vessels",))[0] for v in views}
        out = [replace(v, vessels=(images[v.name] / max(float(images[v.name].max()), 1e-12)).astype(np.float32))
               for v in out]
    return out


def case_errors(case: BenchCase, poses: dict) -> tuple[float, float, float | None]:
    """(rotation error deg, worst view's source-position error mm, mean carotid mPCD mm or None)."""
    e = [evaluate_pose(poses[k], case.true_poses[k], case.runs[k].detector, case.runs[k].angles.sod_mm,
                       case.carotid_points_mm) for k in VIEW_KEYS]
    mpcd = None if case.carotid_points_mm is None else float(np.mean([x["mpcd_mm"] for x in e]))
    return max(x["rotation_error_deg"] for x in e), max(x["source_distance_mm"] for x in e), mpcd


def _cell(err: tuple[float, float, float | None] | None) -> str:
    if err is None:
        return "-"
    rot, src, mpcd = err
    return f"{rot:.1f} / {src:.0f}" + ("" if mpcd is None else f" / {mpcd:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--headsq", help="headsq quarter_sidecar.mhd")
    ap.add_argument("--ge-head", help="the GE head CT DICOM folder")
    ap.add_argument("--seeds", type=seed_range, default=seed_range("0-2"), help="case seeds, e.g. 0-2")
    ap.add_argument("--no-motion", action="store_true", help="simulate the runs without patient motion (no residue)")
    ap.add_argument("--no-noise", action="store_true", help="simulate the runs without quantum noise")
    ap.add_argument("--iterations", type=int, default=25)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=None, help="Markdown file to write the table to")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.no_motion:
        phantom_dsa.MOTION_ROTATION_SD_DEG = phantom_dsa.MOTION_SHIFT_SD_PX = 0.0
    if args.no_noise:
        phantom_dsa.QUANTUM_NOISE_SD = (0.0, 0.0)
    heads = [(name, path, make) for name, path, make in (("headsq", args.headsq, headsq_case),
                                                          ("ge-head", args.ge_head, ge_head_case)) if path]
    if not heads:
        raise SystemExit("give --headsq and/or --ge-head")
    rows, t0 = [], time.perf_counter()
    for name, path, make in heads:
        for arteries in (False, True):
            for seed in args.seeds:
                case = make(path, seed=seed, arteries=arteries)
                prep = prepare_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels)
                renderer = TorchRenderer(prep.volume)
                rig = nominal_poses(case.runs)
                X = case.true_poses["pa"] @ np.linalg.inv(rig["pa"])
                base = tto_views(prep.views, case.true_poses)
                cells = []
                for i, variant in enumerate(VARIANTS):
                    views = _noise_free(base, renderer, rig, X, silhouette=i in (1, 3), vessels=i in (2, 3))
                    if views is None:
                        cells.append(None)
                        continue
                    res = test_time_optimise(renderer, views, TTOSchedule(iterations=args.iterations), rig=rig)
                    cells.append(case_errors(case, res.poses))
                rows.append((case.name, cells))
                print(f"{case.name}: " + "; ".join(_cell(c) for c in cells)
                      + f" ({(time.perf_counter() - t0) / 60:.1f} min)", file=sys.stderr, flush=True)
    left_out = [what for what, flag in (("patient motion (no subtraction residue)", args.no_motion),
                                        ("quantum noise", args.no_noise)) if flag]
    motion = f"without {' or '.join(left_out)}" if left_out else "as the benchmark simulates them"
    lines = [
        f"TTO ({args.iterations} steps) started at the true patient pose of real head CTs, runs simulated {motion}. "
        "Per cell: rotation error (deg) / worst view's source-position error (mm) [/ carotid mPCD (mm), cases with "
        "arteries] of the result; 0 / 0 means the target leaves the optimum at the truth. '-': no vessels.",
        "",
        "| case | " + " | ".join(VARIANTS) + " |",
        "|---|" + "---:|" * len(VARIANTS),
    ]
    lines += [f"| {case} | " + " | ".join(_cell(c) for c in cells) + " |" for case, cells in rows]
    table = "\n".join(lines)
    print(table)
    if args.doc:
        command = (f"python experiments/tto_objective/bench_objective_real.py --headsq {args.headsq} --ge-head {args.ge_head} "
                   f"--seeds {args.seeds[0]}-{args.seeds[-1]}{' --no-motion' if args.no_motion else ''}"
                   f"{' --no-noise' if args.no_noise else ''}")
        args.doc.write_text(f"# Where the objective's optimum lies on real heads\n\n{command}\n\n{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
