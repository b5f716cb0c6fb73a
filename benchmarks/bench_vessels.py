"""The CTA vessel mask ``geopose register`` computes (``geopose.cta.vessel_mask_from_cta``) against phantom
truth, per vessel group: voxel precision and recall, and centreline recall (the share of truth centreline points
within their radius, at least one voxel, of the mask); on held-out phantoms, on the real head CTs
made CTAs with a phantom's arteries, and on the plain real heads (no contrast: the mask should be
empty). Times each mask (wall s, the CPUs this process may use).

    nice .venv/bin/python benchmarks/bench_vessels.py --seeds 5000-5019 --spacing 2 --fine-seeds 5000-5002 \\
        --headsq ../shared/data/headsq/quarter_sidecar.mhd --ge-head ../shared/data/ge_head_ct_tilt \\
        --real-seeds 0-2 --doc experiments/vessel_mask/vessel_segmentation_table.md --json experiments/vessel_mask/vessel_segmentation.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TextIO

import numpy as np
import SimpleITK as sitk

from geopose.bench.cases import seed_range
from geopose.cta import vessel_mask_from_cta
from geopose.phantom import labels as L
from geopose.phantom import make_subject
from geopose.phantom.real_head import load_headsq, with_arteries
from geopose.cta import load_cta
from geopose.volume import Volume

#: Vessel groups scored: name -> artery labels (``phantom.labels``, intracranial variants included).
GROUPS = {
    "ica_left": [L.ICA_LEFT], "ica_right": [L.ICA_RIGHT], "anterior": [L.ANTERIOR_LEFT, L.ANTERIOR_RIGHT],
    "posterior": [L.POSTERIOR], "external": [L.EXTERNAL_LEFT, L.EXTERNAL_RIGHT],
}
#: Non-artery labels a mask should leave out, where the phantom world has them (name -> label values).
DISTRACTORS = {"venous_sinus": (9, 19), "dura": (20,), "nidus": (21,)}


def _distance_mm(mask: np.ndarray, spacing_mm) -> np.ndarray:
    """Distance (mm) of every voxel to ``mask`` ([k, j, i] bool; 0 inside; large where it is empty)."""
    if not mask.any():
        return np.full(mask.shape, 1e9, np.float32)
    image = sitk.GetImageFromArray(mask.astype(np.uint8))
    image.SetSpacing(tuple(float(s) for s in spacing_mm))
    d = sitk.SignedMaurerDistanceMap(image, insideIsPositive=False, squaredDistance=False, useImageSpacing=True)
    return np.maximum(sitk.GetArrayFromImage(d), 0.0)


def score(mask: np.ndarray, labels: Volume, centerlines: list[dict]) -> dict:
    """Precision, recall and centreline recall per group (and all arteries, and the carotids = both
    ICAs) of ``mask`` ([k, j, i] bool on ``labels``' grid); ``centerlines`` in the centred frame (mm)."""
    lab, spacing = labels.array, labels.spacing_mm
    truth = {g: np.isin(lab, L.with_intracranial(v)) for g, v in GROUPS.items()}
    arteries = L.vessel_mask(lab)
    dist_to_group = np.stack([_distance_mm(t, spacing) for t in truth.values()])
    owner = np.argmin(dist_to_group, axis=0)  # each mask voxel belongs to its nearest group
    dist_to_mask = _distance_mm(mask, spacing)
    to_ijk = np.linalg.inv(labels.ijk_to_centred)
    tol_min = max(spacing)
    out: dict = {"mask_voxels": int(mask.sum()), "precision": float((mask & arteries).sum() / max(mask.sum(), 1)),
                 "recall": float((mask & arteries).sum() / max(arteries.sum(), 1))}
    for name, values in DISTRACTORS.items():
        present = np.isin(lab, values)
        if present.any():
            out[f"share_{name}"] = float((mask & present).sum() / max(mask.sum(), 1))
    hits: dict[str, list] = {g: [] for g in GROUPS}
    for line in centerlines:
        group = next((g for g, v in GROUPS.items() if int(line["label"]) in v), None)
        if group is None:
            continue
        pts = np.asarray(line["points_mm"], float)
        ijk = np.rint(pts @ to_ijk[:3, :3].T + to_ijk[:3, 3]).astype(int)
        ok = np.all((ijk >= 0) & (ijk < np.asarray(labels.shape_ijk)), axis=1)
        i, j, k = ijk[ok].T
        tol = np.maximum(np.asarray(line["radii_mm"], float)[ok], tol_min)
        hits[group] += list(dist_to_mask[k, j, i] <= tol)
    for g, (name, t) in enumerate(truth.items()):
        mine = mask & (owner == g)
        out[name] = {"precision": float((mine & t).sum() / max(mine.sum(), 1)) if mine.any() else None,
                     "recall": float((mask & t).sum() / max(t.sum(), 1)) if t.any() else None,
                     "centreline_recall": float(np.mean(hits[name])) if hits[name] else None}
    carotid = hits["ica_left"] + hits["ica_right"]
    out["carotid_centreline_recall"] = float(np.mean(carotid)) if carotid else None
    out["centreline_recall"] = float(np.mean(sum(hits.values(), []))) if any(hits.values()) else None
    return out



def write_scored(out: TextIO, row: dict, mask: np.ndarray, subject) -> dict:
    """``row`` (what the mask is: seed, variant, ...) with :func:`score` of ``mask`` on ``subject`` (a phantom
    ``Subject``: labels and centrelines), written to ``out`` as one JSON line and said on stdout; returns it."""
    row = {**row, **score(mask, subject.labels, subject.centerlines)}
    out.write(json.dumps(row) + "\n")
    out.flush()
    print(*(v for k, v in row.items() if not isinstance(v, dict) and k in ("seed", "variant", "cut")),
          f"P {row['precision']:.3f} R {row['recall']:.3f} carotid clR {row['carotid_centreline_recall']:.3f}", flush=True)
    return row

def timed_mask(cta: Volume) -> tuple[np.ndarray, dict, float]:
    """The vessel mask of ``cta`` (bool), its metadata (``contrast``: a tree was found) and its wall time (s)."""
    t0 = time.perf_counter()
    result = vessel_mask_from_cta(cta)
    return result.array > 0, {"contrast": bool(result.metadata.get("contrast", result.array.any()))}, time.perf_counter() - t0


def phantom_rows(seeds: list[int], spacing_mm: float) -> list[dict]:
    rows = []
    for seed in seeds:
        subject = make_subject(seed, spacing_mm=spacing_mm)
        mask, meta, seconds = timed_mask(subject.cta)
        rows.append({"case": f"phantom-{seed}", "spacing_mm": spacing_mm, "seconds": seconds, "contrast": meta["contrast"],
                     **score(mask, subject.labels, subject.centerlines)})
        print(_line(rows[-1]), flush=True)
    return rows


def real_rows(name: str, cta: Volume, seeds: list[int]) -> list[dict]:
    """The plain real head (no contrast: the mask should be empty) and, per seed, the head made a CTA."""
    mask, meta, seconds = timed_mask(cta)
    voxel_mm3 = float(np.prod(cta.spacing_mm))
    rows = [{"case": name, "spacing_mm": max(cta.spacing_mm), "seconds": seconds, "contrast": meta["contrast"],
             "mask_voxels": int(mask.sum()), "mask_mm3": float(mask.sum() * voxel_mm3)}]
    print(_line(rows[-1]), flush=True)
    for seed in seeds:
        ctaa, labels, lines = with_arteries(cta, seed)
        mask, meta, seconds = timed_mask(ctaa)
        rows.append({"case": f"{name}+arteries-{seed}", "spacing_mm": max(cta.spacing_mm), "seconds": seconds,
                     "contrast": meta["contrast"], **score(mask, labels, lines)})
        print(_line(rows[-1]), flush=True)
    return rows


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.0f}"


def _line(row: dict) -> str:
    if "precision" not in row:
        return f"{row['case']:<24} {row['spacing_mm']:.2g} mm  {row['seconds']:5.1f} s  contrast={row['contrast']}  " \
               f"mask {row['mask_mm3']:.0f} mm3"
    groups = "  ".join(f"{g} {_pct(row[g]['precision'])}/{_pct(row[g]['recall'])}/{_pct(row[g]['centreline_recall'])}"
                       for g in GROUPS)
    extra = "  ".join(f"{k[6:]} {100 * v:.0f}%" for k, v in row.items() if k.startswith("share_"))
    return (f"{row['case']:<24} {row['spacing_mm']:.2g} mm {row['seconds']:5.1f} s  P {_pct(row['precision'])} "
            f"R {_pct(row['recall'])} clR {_pct(row['centreline_recall'])} carotid clR "
            f"{_pct(row['carotid_centreline_recall'])}  | {groups}  | {extra}")


def table(rows: list[dict]) -> list[str]:
    """Markdown: one row per case, then the mean per block of cases (phantoms per spacing, real heads)."""
    head = ("| case | grid mm | s | precision | recall | centreline recall | carotid cl. recall | "
            + " | ".join(f"{g} P/R/clR" for g in GROUPS) + " | venous / dura share |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for row in rows:
        if "precision" not in row:
            lines.append(f"| {row['case']} (no contrast) | {row['spacing_mm']:.2g} | {row['seconds']:.1f} | mask "
                         f"{row['mask_mm3']:.0f} mm3, contrast={row['contrast']} |" + " |" * (len(GROUPS) + 4))
            continue
        groups = " | ".join(f"{_pct(row[g]['precision'])} / {_pct(row[g]['recall'])} / {_pct(row[g]['centreline_recall'])}"
                            for g in GROUPS)
        distract = " / ".join(_pct(row.get(f"share_{k}")) for k in ("venous_sinus", "dura"))
        lines.append(f"| {row['case']} | {row['spacing_mm']:.2g} | {row['seconds']:.1f} | {_pct(row['precision'])} | "
                     f"{_pct(row['recall'])} | {_pct(row['centreline_recall'])} | {_pct(row['carotid_centreline_recall'])} | "
                     f"{groups} | {distract} |")
    blocks: dict[str, list[dict]] = {}
    for row in rows:
        if "precision" in row:
            key = f"phantoms at {row['spacing_mm']:g} mm" if row["case"].startswith("phantom") else "real heads + arteries"
            blocks.setdefault(key, []).append(row)
    for key, picked in blocks.items():
        def mean(f) -> float:
            values = [v for v in (f(r) for r in picked) if v is not None]
            return float(np.mean(values)) if values else float("nan")
        groups = " | ".join(f"{100 * mean(lambda r: r[g]['precision']):.0f} / {100 * mean(lambda r: r[g]['recall']):.0f} / "
                            f"{100 * mean(lambda r: r[g]['centreline_recall']):.0f}" for g in GROUPS)
        lines.append(f"| **mean, {key} (n={len(picked)})** | | {mean(lambda r: r['seconds']):.1f} | "
                     f"**{100 * mean(lambda r: r['precision']):.0f}** | {100 * mean(lambda r: r['recall']):.0f} | "
                     f"{100 * mean(lambda r: r['centreline_recall']):.0f} | **{100 * mean(lambda r: r['carotid_centreline_recall']):.0f}** | "
                     f"{groups} | |")
    return lines


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="5000-5019", help="phantom seeds at --spacing")
    p.add_argument("--spacing", type=float, default=2.0)
    p.add_argument("--fine-seeds", default="", help="phantom seeds also scored at 1 mm")
    p.add_argument("--headsq", help="quarter_sidecar.mhd of the real head CT headsq")
    p.add_argument("--ge-head", help="folder of the real GE head CT DICOM series")
    p.add_argument("--real-seeds", default="0-2", help="phantom seeds whose arteries the real heads get")
    p.add_argument("--doc", help="write the markdown table here")
    p.add_argument("--json", help="write the rows here")
    args = p.parse_args()
    rows = phantom_rows(seed_range(args.seeds), args.spacing) if args.seeds else []
    if args.fine_seeds:
        rows += phantom_rows(seed_range(args.fine_seeds), 1.0)
    real_seeds = seed_range(args.real_seeds) if args.real_seeds else []
    if args.headsq:
        rows += real_rows("headsq", load_headsq(args.headsq), real_seeds)
    if args.ge_head:
        rows += real_rows("ge-head", load_cta(args.ge_head), real_seeds)
    lines = table(rows)
    print("\n".join(lines))
    if args.doc:
        Path(args.doc).write_text("python benchmarks/bench_vessels.py " + " ".join(sys.argv[1:]) + "\n\n" + "\n".join(lines) + "\n")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
