"""Does the fit's precision tell a wrong pairing? Statistics of the vessel fit at the registered pose.

For each seed s: ``register_and_write`` (the user's path, CTA and runs only) with the CTA of s and the runs of the
next seed (crossed), and with the CTA and runs of s (correct). At the final pose, per view, on the TTO's detector:
the CTA's kept vessels (the opacified read, as the objective judges them) against the run's vessel image:

* ``ncc_s{σ}``: their NCC after a Gaussian blur of σ px on both; ``ncc_m{σ}``: with the CTA's vessels alone blurred
  (the run's noise, uncorrelated with either, lowers both NCCs alike);
* ``shift_rms_mm`` / ``shift_median_mm``: in 4 x 4 blocks where both show vessels, the shift (±6 px, sub-pixel) that best
  aligns the block, at the detector (mm), its weighted RMS and median over the blocks (the run's vessel energy weighs);
* ``local_gain``: the NCC of the run's vessel image with the CTA's vessels moved block by block by those (whole-pixel)
  shifts, over their NCC as registered: what a fit beyond one rigid pose would gain.

    python fit_precision.py PHANTOM_DIR OUT_DIR ROWS.jsonl SEED [SEED ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from geopose.images import gaussian_blur
from geopose.metrics.similarity import ncc
from geopose.register.cli import register_and_write
from geopose.register.opacified import selection_judge

BLOCKS, MAX_SHIFT_PX = 4, 6


def block_shifts(drr: np.ndarray, run: np.ndarray, aligned: np.ndarray | None = None) -> list[tuple[float, float, float]]:
    """(dy, dx, weight) per block: the shift of ``drr`` that best matches ``run`` there (px); ``aligned`` (a copy of
    ``drr``) receives each such block moved by its whole-pixel shift."""
    h, w = run.shape
    bh, bw = h // BLOCKS, w // BLOCKS
    pad = np.pad(drr, MAX_SHIFT_PX)
    out = []
    energy = float((run ** 2).sum())
    for i in range(BLOCKS):
        for j in range(BLOCKS):
            tgt = run[i * bh:(i + 1) * bh, j * bw:(j + 1) * bw]
            src0 = drr[i * bh:(i + 1) * bh, j * bw:(j + 1) * bw]
            if tgt.std() < 1e-6 or src0.std() < 1e-6 or (tgt ** 2).sum() < 0.01 * energy:
                continue
            scores = np.full((2 * MAX_SHIFT_PX + 1,) * 2, -1.0)
            for dy in range(-MAX_SHIFT_PX, MAX_SHIFT_PX + 1):
                for dx in range(-MAX_SHIFT_PX, MAX_SHIFT_PX + 1):
                    y0, x0 = i * bh + MAX_SHIFT_PX - dy, j * bw + MAX_SHIFT_PX - dx
                    scores[dy + MAX_SHIFT_PX, dx + MAX_SHIFT_PX] = ncc(tgt, pad[y0:y0 + bh, x0:x0 + bw])
            k, l = np.unravel_index(int(np.argmax(scores)), scores.shape)
            if aligned is not None:
                y0, x0 = i * bh + MAX_SHIFT_PX - (k - MAX_SHIFT_PX), j * bw + MAX_SHIFT_PX - (l - MAX_SHIFT_PX)
                aligned[i * bh:(i + 1) * bh, j * bw:(j + 1) * bw] = pad[y0:y0 + bh, x0:x0 + bw]
            sub = []
            for axis, c in ((0, k), (1, l)):
                if 0 < c < scores.shape[axis] - 1:
                    a, b, d = (scores[c - 1, l], scores[c, l], scores[c + 1, l]) if axis == 0 else (scores[k, c - 1], scores[k, c], scores[k, c + 1])
                    den = a - 2 * b + d
                    sub.append(c + (0.5 * (a - d) / den if den < 0 else 0.0))
                else:
                    sub.append(float(c))
            out.append((sub[0] - MAX_SHIFT_PX, sub[1] - MAX_SHIFT_PX, float((tgt ** 2).sum())))
    return out


def view_stats(judge, pose, prepared) -> dict:
    drr = judge.render(pose, prepared.tto_detector, ("vessels",))[0].astype(np.float64)
    run = np.asarray(prepared.tto_vessels, np.float64)
    stats = {f"ncc_s{s}": ncc(gaussian_blur(run, (s, s)), gaussian_blur(drr, (s, s))) for s in (0, 1, 2, 4)}
    stats |= {f"ncc_m{s}": ncc(run, gaussian_blur(drr, (s, s))) for s in (1, 2, 4)}
    aligned = drr.copy()
    shifts = block_shifts(drr, run, aligned)
    stats["local_gain"] = ncc(run, aligned) / max(stats["ncc_s0"], 1e-6)
    px_mm = float(np.mean(prepared.tto_detector.spacing_mm))
    if shifts:
        d = np.array([[a, b] for a, b, _ in shifts]) * px_mm
        w = np.array([c for *_, c in shifts])
        r = np.hypot(d[:, 0], d[:, 1])
        stats |= {"shift_rms_mm": float(np.sqrt((w * r ** 2).sum() / w.sum())), "shift_median_mm": float(np.median(r)),
                  "blocks": len(shifts)}
    return stats


def main(argv: list[str]) -> None:
    phantoms, out, rows_path, seeds = Path(argv[0]), Path(argv[1]), Path(argv[2]), [int(s) for s in argv[3:]]
    for i, s in enumerate(seeds):
        for runs_seed in (seeds[(i + 1) % len(seeds)], s):
            done = register_and_write(phantoms / str(s) / "cta.nii.gz", phantoms / str(runs_seed) / "dsa_pa.dcm",
                                      phantoms / str(runs_seed) / "dsa_lat.dcm", out / f"{s}_{runs_seed}", progress=lambda *a: None)
            case = done.case
            judge = selection_judge(case.renderer, case.registration.vessel_selection)
            views = {k: view_stats(judge, v.final_pose, v.prepared) | {"flag": v.quality.flag} for k, v in case.views.items()}
            m = case.registration.mirror
            row = {"cta": s, "runs": runs_seed, "crossed": s != runs_seed, "views": views,
                   "mirror_margin": None if m is None else m.margin,
                   "equal_effort_margin": None if m is None else m.equal_effort_margin,
                   "mpcd_mm": None if s != runs_seed else {k: done.record["views"][k]["truth"]["final"]["mpcd_mm"] for k in views}}
            with rows_path.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(s, runs_seed, {k: (v["flag"], round(v["ncc_s0"], 3), round(v["ncc_s2"], 3), round(v.get("shift_rms_mm", -1), 2),
                                     round(v.get("shift_median_mm", -1), 2)) for k, v in views.items()}, flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
