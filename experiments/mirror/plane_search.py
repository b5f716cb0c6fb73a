"""The midsagittal plane search (``cta/symmetry.py``) against a slower reference search on the same CTAs: the
plane found (yaw, roll, deg; shift along the normal, mm), its symmetry NCC and the seconds, on held-out phantoms'
work grids (2 mm) and the real heads in ``../shared/data``. The reference is the search as it was until session 44:
a 2.5-deg grid of 13 x 13 on the coarse grid, then two refinements of 5 x 5 x 3 (1.0 and 0.5 deg / mm) on the
fine grid (319 resamples).

    .venv/bin/python experiments/mirror/plane_search.py --seeds 6010-6029 --headsq ../shared/data/headsq/quarter_sidecar.mhd \
        --ge-head ../shared/data/ge_head_ct_tilt > rows.jsonl
"""
import json
import sys
import time
from itertools import product
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import argparse  # noqa: E402
import tempfile  # noqa: E402

import heldout  # noqa: E402,F401  (geopose before torch)
from geopose.bench.cases import ge_head_case, headsq_case, phantom_case, seed_range  # noqa: E402
from geopose.cta import symmetry as S  # noqa: E402
from geopose.cta.io import sitk_from_volume  # noqa: E402
from geopose.render.volume import render_factors  # noqa: E402


def reference_plane(cta) -> S.Midplane:
    """The search as it was until session 44 (319 resamples)."""
    full = sitk.Clamp(sitk.Cast(sitk_from_volume(cta), sitk.sitkFloat32), sitk.sitkFloat32, *S.SYMMETRY_WINDOW_HU)
    factors = [max(1, int(round(S.SYMMETRY_GRID_MM / s))) for s in full.GetSpacing()]
    fine, coarse = sitk.BinShrink(full, factors), sitk.BinShrink(full, [2 * f for f in factors])
    values = sitk.GetArrayViewFromImage(fine)
    kji = np.argwhere(values > S.BODY_HU).mean(axis=0)
    centre = np.array(fine.TransformContinuousIndexToPhysicalPoint(kji[::-1].tolist()))
    coarse_score, fine_score = S._symmetry_score(coarse, centre), S._symmetry_score(fine, centre)
    angles = np.arange(-S.MAX_TILT_DEG, S.MAX_TILT_DEG + 1e-9, 2.5)
    best = max((coarse_score(yaw, roll, 0.0), yaw, roll, 0.0) for yaw, roll in product(angles, angles))
    for step in (1.0, 0.5):
        _, yaw0, roll0, shift0 = best
        best = max((fine_score(yaw0 + a * step, roll0 + b * step, shift0 + c * step), yaw0 + a * step, roll0 + b * step,
                    shift0 + c * step) for a, b, c in product((-2, -1, 0, 1, 2), (-2, -1, 0, 1, 2), (-2, 0, 2)))
    ncc, yaw, roll, shift = best
    return S.Midplane(S._normal(yaw, roll), centre + shift * S._normal(yaw, roll), float(yaw), float(roll), ncc)


def row(name: str, cta) -> dict:
    """Both searches' planes of ``cta`` and seconds; ``offset_mm``: how far along its normal each plane lies from the
    reference plane's point (0 for the reference)."""
    out, reference = {"case": name}, None
    for label, search in (("reference", reference_plane), ("product", S.midsagittal_plane)):
        t0 = time.perf_counter()
        plane = search(cta)
        seconds = time.perf_counter() - t0
        reference = reference or plane
        out[label] = {"yaw_deg": plane.yaw_deg, "roll_deg": plane.roll_deg, "ncc": round(plane.symmetry_ncc, 5),
                      "offset_mm": round(float((plane.point_lps_mm - reference.point_lps_mm) @ plane.normal_lps), 3),
                      "s": round(seconds, 3)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seed_range, default=seed_range("6010-6029"))
    ap.add_argument("--headsq")
    ap.add_argument("--ge-head")
    args = ap.parse_args()
    heads = [make(path, seed=0, arteries=True) for path, make in ((args.headsq, headsq_case), (args.ge_head, ge_head_case))
             if path]
    for case in heads:  # about the TTO's finest level on a CPU (2 mm), as the mirror test sees the CTA
        print(json.dumps(row(case.name, case.cta.shrunk(render_factors(case.cta.spacing_mm, 2.0)))), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            case = phantom_case(seed, Path(tmp) / str(seed), 2.0)
            print(json.dumps(row(case.name, case.cta)), flush=True)


if __name__ == "__main__":
    main()
