"""What the canal pieces bridged to the tree across their mouths are (2026-12-06, session 50; ``canal_mouth.md``).

For each phantom, the CTA vessel mask is computed as ``register_case`` does (``vessel_mask_from_cta``). Its inputs to
``masks._canal_mouths`` (the tree, the canal, the tube measure, the near-bone lumen) are recorded, and every piece of
canal + mouths that touches the tree is scored against the phantom's labels. A piece's row gives its voxels, its
artery / vein / cranium-without-vessel (bone, in lumen HU: marrow and diploe) shares, its canal voxels' mean tube measure and whether the rule keeps it. One JSON line per piece.

    .venv/bin/python experiments/vessel_mask/canal_pieces.py --seeds 6010-6029 > pieces.jsonl
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import SimpleITK as sitk

from geopose.bench.cases import seed_range
from geopose.cta import masks as M
from geopose.phantom import labels as L
from geopose.phantom import make_subject

VEINS = (L.VENOUS_SINUS, L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seed_range, default=seed_range("6010-6029"))
    ap.add_argument("--spacing-mm", type=float, default=1.0)
    args = ap.parse_args()
    seen: dict = {}
    body_box, canal_mouths = M._body_box, M._canal_mouths

    def box(body, spacing_mm):
        seen["box"] = body_box(body, spacing_mm)
        return seen["box"]

    def mouths(tree, canal, tubes, near_bone_lumen, spacing_mm):
        seen.update(tree=tree, canal=canal, tubes=tubes, near_bone_lumen=near_bone_lumen, spacing_mm=spacing_mm)
        seen["kept"] = canal_mouths(tree, canal, tubes, near_bone_lumen, spacing_mm)
        return seen["kept"]

    M._body_box, M._canal_mouths = box, mouths
    for seed in args.seeds:
        subject = make_subject(seed, spacing_mm=args.spacing_mm)
        M.vessel_mask_from_cta(subject.cta)
        labels = subject.labels.array[seen["box"]]
        tree, canal, tubes, spacing_mm = seen["tree"], seen["canal"], seen["tubes"], seen["spacing_mm"]
        bridged = seen["near_bone_lumen"] & M._dilate_mm(tree, M.CANAL_MOUTH_MM, spacing_mm) & M._dilate_mm(canal, M.CANAL_MOUTH_MM, spacing_mm)
        pieces = sitk.GetArrayFromImage(sitk.ConnectedComponent(sitk.GetImageFromArray((canal | bridged).astype(np.uint8)), True))
        touching = np.unique(pieces[M._dilate_mm(tree, 1.0, spacing_mm) & (pieces > 0)])
        arteries = L.vessel_mask(labels)
        for piece in touching.tolist():
            inside = pieces == piece
            print(json.dumps({
                "seed": seed, "voxels": int(inside.sum()), "artery": round(float(arteries[inside].mean()), 3),
                "vein": round(float(np.isin(labels[inside], VEINS).mean()), 3),
                "cranium_no_vessel": round(float((labels[inside] == L.CRANIUM).mean()), 3),
                "mean_tube_measure": round(float(tubes[inside & canal].mean()), 4),
                "kept": bool(seen["kept"][inside].any())}), flush=True)


if __name__ == "__main__":
    main()
