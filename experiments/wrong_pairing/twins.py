"""How alike the phantom world's subjects are: why a wrong pairing or a mirrored CTA can fit like the right one.

For each subject s, the arteries a right-CCA run shows (labels ICA, anterior and external right; the random cortical
branches left out), each named artery resampled to 40 points by arc length in the head frame (mm), fitted rigidly
(Kabsch) onto the same named arteries of another anatomy: subject s + 1 (the wrong pairing ``geopose bench
--crossed-subjects`` registers: s's CTA, s + 1's runs) and s mirrored left-right (its left arteries reflected, standing
for its right ones: what a mirrored CTA shows). The RMS distance after the fit is how far the other anatomy's arteries
lie from the run's at the best rigid pose; beside it the pairing test's gain of that case in a bench's case records.

    python twins.py FIRST_SEED LAST_SEED [BENCH_CASES_DIR]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from geopose.phantom.anatomy import sample_head
from geopose.training.canonical import nearest_rotation

#: The centreline labels of the arteries a right-CCA run opacifies (``phantom/labels.py``: ICA, anterior, external right).
SHOWN_LABELS = (3, 5, 8)


def named_arteries(seed: int) -> tuple[dict[str, np.ndarray], set[str]]:
    """Subject ``seed``'s named arteries (name -> (N, 3) head-frame mm) and the names a right-CCA run shows."""
    params = sample_head(np.random.default_rng(seed), seed)
    named = [a for a in params.arteries if not a["name"].startswith("cortical")]
    return ({a["name"]: np.asarray(a["points"], float) for a in named},
            {a["name"] for a in named if int(a["label"]) in SHOWN_LABELS})


def mirrored(arteries: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Left and right swapped: each artery reflected across x = 0 under its other side's name."""
    swap = {"_left": "_right", "_right": "_left"}
    out = {}
    for name, points in arteries.items():
        side = next((s for s in swap if name.endswith(s)), None)
        out[name[: -len(side)] + swap[side] if side else name] = points * np.array([-1.0, 1.0, 1.0])
    return out


def resampled(points: np.ndarray, n: int = 40) -> np.ndarray:
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    t = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(t, arc, points[:, i]) for i in range(3)], 1)


def rigid_rms_mm(run_side: dict[str, np.ndarray], cta_side: dict[str, np.ndarray], shown: set[str]) -> float:
    """RMS distance (mm) of corresponding points after the best rigid fit (Kabsch, no scaling)."""
    names = sorted(shown & set(cta_side))
    P = np.vstack([resampled(run_side[n]) for n in names])
    Q = np.vstack([resampled(cta_side[n]) for n in names])
    P, Q = P - P.mean(0), Q - Q.mean(0)
    R = nearest_rotation(P.T @ Q)  # Kabsch: the rotation nearest the points' cross-covariance
    return float(np.sqrt(np.mean(np.sum((P @ R - Q) ** 2, axis=1))))


def gain(cases: Path | None, name: str) -> float | None:
    try:
        return json.loads((cases / f"{name}.json").read_text())["pairing"]["gain"]
    except (TypeError, OSError, KeyError):
        return None


def main(argv: list[str]) -> None:
    first, last = int(argv[0]), int(argv[1])
    cases = Path(argv[2]) if len(argv) > 2 else None
    print("| subject | wrong pairing (s's CTA, s+1's runs): RMS (mm) | its gain | mirrored CTA: RMS (mm) | its gain |")
    print("|---|---:|---:|---:|---:|")
    for seed in range(first, last + 1):
        (own, shown), (runs, runs_shown) = named_arteries(seed), named_arteries(seed + 1)
        crossed = rigid_rms_mm(runs, own, runs_shown)
        mirror = rigid_rms_mm(own, mirrored(own), shown)
        g1 = gain(cases, f"phantom-{seed}-cta+phantom-{seed + 1}-runs")
        g2 = gain(cases, f"phantom-{seed}-mirrored")
        print(f"| {seed} | {crossed:.2f} | {'' if g1 is None else f'{g1:.3f}'} | {mirror:.2f} | {'' if g2 is None else f'{g2:.3f}'} |")


if __name__ == "__main__":
    main(sys.argv[1:])
