"""How far do the pieces of the computed vessel mask reach along the superior axis, with and without contrast? For
held-out phantoms (2 mm) and the real head CTs without contrast: the two longest components' spans (mm) of the mask
computed from the CTA (``cta/masks.py``), and, on phantoms, of that mask's arteries alone (as a CTA whose sinuses do
not enhance would give), with the product's decision and that of a rule tried and not kept (``PAIR_SPAN_MM``). A
Markdown table.

    .venv/bin/python experiments/vessel_mask/contrast_span.py --seeds 6010-6034 6038 --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt --real-seeds 0-5 --doc experiments/vessel_mask/contrast_span_table.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Logic"))

from geopose.bench.cases import ge_head_case, headsq_case, phantom_case, seed_range  # noqa: E402
from geopose.cta import masks  # noqa: E402
from geopose.cta.io import load_cta  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402


def two_longest_mm(mask: np.ndarray, spacing_mm, axis: int) -> tuple[float, float]:
    """The two longest extents (mm) along array ``axis`` of the 26-connected components of ``mask`` ([k, j, i])."""
    shapes = sitk.LabelShapeStatisticsImageFilter()
    shapes.Execute(sitk.ConnectedComponent(sitk.GetImageFromArray(mask.astype(np.uint8)), True))
    dim = 2 - axis
    spans = sorted((shapes.GetBoundingBox(label)[3 + dim] * spacing_mm[dim] for label in shapes.GetLabels()), reverse=True)
    return tuple((spans + [0.0, 0.0])[:2])


#: The rule tried and not kept (contrast_span.md): contrast also when the two longest pieces together span this (mm).
PAIR_SPAN_MM = 140.0


def decided(spans: tuple[float, float], pair: bool) -> str:
    """The product's decision (``pair`` False) or the tried rule's."""
    return "contrast" if spans[0] >= masks.CONTRAST_SPAN_MM or (pair and sum(spans) >= PAIR_SPAN_MM) else "none"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", nargs="+", type=seed_range, default=[seed_range("6010-6034")])
    ap.add_argument("--spacing-mm", type=float, default=2.0)
    ap.add_argument("--headsq", type=Path)
    ap.add_argument("--ge-head", type=Path)
    ap.add_argument("--real-seeds", type=seed_range, default=[], help="the real heads with phantom arteries fitted in, "
                    "these run seeds (e.g. 0-5)")
    ap.add_argument("--doc", type=Path)
    args = ap.parse_args()
    captured = {}
    rule = masks._vessel_mask

    def spy(a, spacing_mm, axis):  # the mask on its working grid, before the contrast decision
        small, longest_mm = rule(a, spacing_mm, axis)
        captured.update(mask=small > 0, spacing=spacing_mm, axis=axis, spans=two_longest_mm(small > 0, spacing_mm, axis))
        return small, longest_mm

    masks._vessel_mask = spy
    lines = [f"Two longest pieces of the computed vessel mask along the superior axis (mm), and the decisions (product: "
             f"contrast when one piece spans >= {masks.CONTRAST_SPAN_MM:g} mm; tried: or the two together >= "
             f"{PAIR_SPAN_MM:g} mm):", "",
             "| case | mask | product | tried | its arteries alone (phantom labels) | product | tried |",
             "|---|---:|---|---|---:|---|---|"]
    for seed in sorted({s for group in args.seeds for s in group}):
        with tempfile.TemporaryDirectory() as tmp:
            case = phantom_case(seed, Path(tmp), args.spacing_mm)
            labels = load_cta(Path(tmp) / "labels.nii.gz", check_hu=False).array
        masks.vessel_mask_from_cta(case.cta)
        spans = captured["spans"]
        arteries = two_longest_mm(captured["mask"] & L.vessel_mask(labels), captured["spacing"], captured["axis"])
        lines.append(f"| {case.name} | {spans[0]:.0f} + {spans[1]:.0f} | {decided(spans, False)} | {decided(spans, True)} | "
                     f"{arteries[0]:.0f} + {arteries[1]:.0f} | {decided(arteries, False)} | {decided(arteries, True)} |")
    heads = []
    for label, path, make in (("headsq", args.headsq, headsq_case), ("GE head", args.ge_head, ge_head_case)):
        if path:
            heads += [(f"{label} (no contrast)", lambda make=make, path=path: make(path).cta)]
            heads += [(f"{label} + arteries, seed {seed}", lambda make=make, path=path, seed=seed: make(path, seed, arteries=True).cta)
                      for seed in args.real_seeds]
    for name, make in heads:
        masks.vessel_mask_from_cta(make())
        spans = captured["spans"]
        lines.append(f"| {name} | {spans[0]:.0f} + {spans[1]:.0f} | {decided(spans, False)} | {decided(spans, True)} | - | - | - |")
    text = "\n".join(lines) + "\n"
    (args.doc.write_text(text) if args.doc else sys.stdout.write(text))


if __name__ == "__main__":
    main()
