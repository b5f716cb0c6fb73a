"""Where the computed vessel mask misses the carotid centrelines of validation phantoms, and why: each run of missed
points along an ICA with its length, height, HU, and the share of its points in the candidate tree, dense bone, the
bone mask (with the marrow it rings), the bone margin, the air margin, the body and the lumen HU range; the artery
classifier's p and the tube measure (medians).

    .venv/bin/python experiments/vessel_mask/canal_bridge/carotid_misses.py 6025 6032
"""
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import geopose  # noqa: F401  (before torch)
from geopose.cta import masks as M
from geopose.cta.arteries import artery_features, load_artery_classifier
from geopose.phantom import make_subject
from geopose.phantom import labels as L
sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))
from bench_vessels import _distance_mm

clf = load_artery_classifier()
for seed in [int(s) for s in sys.argv[1:]]:
    sub = make_subject(seed, spacing_mm=1.0)
    vol = sub.cta
    a = np.asarray(vol.array, np.float32)
    sp = vol.spacing_mm
    axis = M._superior_array_axis(vol)
    # intermediates (whole grid; the product uses the body box, same result)
    body = sitk.GetArrayFromImage(M._largest_component(sitk.GetImageFromArray((a > M.BODY_HU).astype(np.uint8)))).astype(bool)
    body = M._fill_slicewise(body, axis).astype(bool)
    near_air = M._dilate_mm(body & (a < M.BODY_HU), M.AIR_MARGIN_MM, sp)
    bodyE = M._eroded_by_ball(body, M._radius_vox(M.BODY_SURFACE_MM, sp))
    in_plane = float(np.prod([s for n, s in enumerate(sp) if n != 2 - axis]))
    dense = a > M.DENSE_BONE_HU
    bone = dense | M._small_holes_slicewise(dense, axis, M.MARROW_MAX_MM2 / in_plane)
    near_bone = M._dilate_mm(bone, M.BONE_MARGIN_MM, sp)
    lo, hi = M.VESSEL_HU_RANGE
    lumen = (a >= lo) & (a <= hi)
    tubes = M._tube_measure(a, sp)
    work, tree, _ = M.vessel_candidates(vol)
    feats, idx = artery_features(work, tree, np.asarray(M.cranium_mask_from_cta(work).array) > 0)
    p = clf.probability(feats)
    pmap = np.full(tree.shape, -1.0, np.float32); pmap[tuple(idx.T)] = p
    kept = np.zeros(tree.shape, bool); kept[tuple(idx[p >= clf.threshold].T)] = True
    d_kept = _distance_mm(kept, sp); d_tree = _distance_mm(tree, sp)
    to_ijk = np.linalg.inv(sub.labels.ijk_to_centred)
    for line in sub.centerlines:
        if int(line["label"]) not in (L.ICA_LEFT, L.ICA_RIGHT):
            continue
        pts = np.asarray(line["points_mm"], float)
        ijk = np.rint(pts @ to_ijk[:3, :3].T + to_ijk[:3, 3]).astype(int)
        tol = np.maximum(np.asarray(line["radii_mm"], float), 1.0)
        i, j, k = ijk.T
        miss = d_kept[k, j, i] > tol
        if not miss.any():
            continue
        # runs of misses
        n = len(pts); s = 0
        while s < n:
            if not miss[s]:
                s += 1; continue
            e = s
            while e + 1 < n and miss[e + 1]:
                e += 1
            seg = slice(s, e + 1)
            kk, jj, ii = k[seg], j[seg], i[seg]
            cause = []
            intree = d_tree[kk, jj, ii] <= tol[seg]
            L_ = np.linalg.norm(np.diff(pts[seg], axis=0), axis=1).sum() if e > s else 0
            print(f"{seed} {line['name']:<12} pts {s}-{e} ({L_:.0f} mm) z {pts[s,2]:.0f}..{pts[e,2]:.0f} "
                  f"r {tol[seg].mean():.1f} HU {np.median(a[kk,jj,ii]):.0f} inTree {intree.mean():.2f} "
                  f"p {np.median(pmap[kk,jj,ii]):.2f} dense {dense[kk,jj,ii].mean():.2f} bone {bone[kk,jj,ii].mean():.2f} "
                  f"nearBone {near_bone[kk,jj,ii].mean():.2f} nearAir {near_air[kk,jj,ii].mean():.2f} "
                  f"bodyE {bodyE[kk,jj,ii].mean():.2f} lumen {lumen[kk,jj,ii].mean():.2f} tube {np.median(tubes[kk,jj,ii]):.3f}", flush=True)
            s = e + 1
