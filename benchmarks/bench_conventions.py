"""Left and right on real data (docs/conventions.md, section 7): the figure and the numbers.

* Figure ``docs/conventions_isoposes.png``: two real head CTs (headsq; the GE head, resampled
  from its tilted slices) rendered by our DRR at LAT- / PA / LAT+, each labelled with the DICOM
  PositionerPrimaryAngle it stands for, beside the GeoPose authors' published real PA and
  lateral; the face (and in the PA the patient's right) marked.
* Table: our renders against DiffDRR 0.6.x ``read()`` of the same CT written as a NIfTI file
  (NCC with its render and with its mirror image), when DiffDRR imports.
* Table: face side by three measures (projected anterior point, rendered teeth, cranium-floor
  slope of the rendered cranium silhouette) at LAT- / LAT+, and the floor slope of the
  published lateral's cranium mask.
* Table: the model camera's approximation (source on the detector's side, section 7): how far
  DICOM's projection of intracranial points lies from ours at the same angles and from ours at
  the best-fitting pose.

Usage (from the repository root; DiffDRR rows need ``.venv-diffdrr``)::

    .venv-diffdrr/bin/python benchmarks/bench_conventions.py --out docs
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conventions_common import (  # noqa: E402
    REPO, dicom_pixels, face_side_of_lateral_cranium_mask, face_side_of_render, ge_head_volume, teeth_and_head_labels,
)

from geopose import contract as C  # noqa: E402
from geopose.phantom.real_head import load_headsq  # noqa: E402
from geopose.cta import cranium_mask_from_cta, save_volume  # noqa: E402
from geopose.geometry import (  # noqa: E402
    CArmAngles, Detector, RigidTransform, isopose, pose_from_carm_angles, project_points, project_points_tensor,
)
from geopose.render import DRR  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

SHARED = REPO.parent / "shared" / "data"
VIEWS = (C.VIEW_LAT_MINUS, C.VIEW_PA, C.VIEW_LAT_PLUS)
#: DICOM PositionerPrimaryAngle (deg) of each view's isopose under docs/conventions.md.
VIEW_PRIMARY_DEG = {C.VIEW_LAT_MINUS: -90.0, C.VIEW_PA: 0.0, C.VIEW_LAT_PLUS: 90.0}
VIEW_WORDS = {C.VIEW_LAT_MINUS: "RAO 90", C.VIEW_PA: "frontal", C.VIEW_LAT_PLUS: "LAO 90"}
#: Length (mm) of the anterior / right marker vectors drawn from the head centre.
MARKER_MM = 70.0
#: Acquisition-like geometry of the approximation table (SID, SOD mm).
SID_MM, SOD_MM = 1100.0, 750.0


def heads() -> dict[str, tuple]:
    """name -> (CT Volume, teeth/head labels or None, cranium mask)."""
    out = {}
    hsq = load_headsq(SHARED / "headsq" / "quarter_sidecar.mhd")
    out["headsq"] = (hsq, teeth_and_head_labels(hsq), cranium_mask_from_cta(hsq))
    ge = ge_head_volume(SHARED / "ge_head_ct_tilt")
    out["GE head"] = (ge, None, cranium_mask_from_cta(ge))
    return out


def head_centre_mm(cta) -> np.ndarray:
    k, j, i = np.nonzero(cta.array > -300.0)
    return (cta.ijk_to_centred @ np.stack((i.mean(), j.mean(), k.mean(), 1.0)))[:3]


def project(pose, det: Detector, pts_mm: np.ndarray) -> np.ndarray:
    rc, _ = project_points(np.asarray(pose, dtype=np.float64).reshape(4, 4), det, pts_mm)
    return rc


def render_views(cta, cranium, det: Detector) -> dict:
    """Per view: image, cranium silhouette, projected head centre, anterior and right points."""
    drr = DRR.from_volume(cta, det, cranium, {"cranium": [1]})
    centre = head_centre_mm(cta)
    out = {}
    for v in VIEWS:
        pose = torch.as_tensor(isopose(v))[None]
        with torch.no_grad():
            img = drr(pose)[0].numpy()
        pts = project(pose, det, np.stack([centre, centre + (0, MARKER_MM, 0), centre + (MARKER_MM, 0, 0)]))
        out[v] = {"image": img[0], "cranium": img[1] > 0.05 * img[1].max(), "centre": pts[0], "anterior": pts[1], "right": pts[2]}
    return out


def face_table(name: str, cta, labels, views: dict, det: Detector) -> list[dict]:
    rows = []
    for v in (C.VIEW_LAT_MINUS, C.VIEW_LAT_PLUS):
        r = views[v]
        row = {
            "head": name, "view": C.VIEW_NAMES[v], "dicom": VIEW_WORDS[v],
            "anterior_point_side": float(np.sign(r["anterior"][1] - r["centre"][1])),
            "cranium_floor_side": face_side_of_lateral_cranium_mask(r["cranium"]),
        }
        if labels is not None:
            row["teeth_side"] = float(np.sign(face_side_of_render(cta, labels, torch.as_tensor(isopose(v))[None], det)))
        rows.append(row)
    return rows


def diffdrr_table(name: str, cta, det: Detector) -> list[dict]:
    """NCC of our isopose renders with DiffDRR's render of the NIfTI file, and with its mirror."""
    try:
        from diffdrr.data import read
        from diffdrr.drr import DRR as DiffDRR
    except Exception:  # ImportError, or a dependency that fails to load
        return []
    from geopose.cta import load_cta

    with tempfile.TemporaryDirectory() as tmp:
        path = save_volume(cta, Path(tmp) / "ct_0000.nii.gz")
        theirs = DiffDRR(read(str(path)), sdd=det.sdd_mm, height=det.rows, delx=det.spacing_mm[1])
        ours = DRR.from_volume(load_cta(path), det)
        rows = []
        for v in VIEWS:
            r = torch.tensor([[C.VIEW_ANCHOR_RAD[v], 0.0, 0.0]])
            t = torch.tensor([C.ISO_TRANSLATION_MM])
            with torch.no_grad():
                d = theirs(r, t, parameterization="euler_angles", convention="ZYX")[0, 0].double()
                a = ours(torch.as_tensor(isopose(v))[None])[0, 0].double()
            rows.append({"head": name, "view": C.VIEW_NAMES[v], "ncc": _ncc(a, d), "ncc_mirrored": _ncc(a.flip(-1), d)})
    return rows


def _ncc(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.flatten(), b.flatten()
    return float((((a - a.mean()) / a.std()) * ((b - b.mean()) / b.std())).mean())


def approximation_table(cta, cranium, det: Detector) -> list[dict]:
    """DICOM's projection (real source, image seen from the detector) against the model camera
    (source on the detector's side) for intracranial points, in mm at the isocentre plane."""
    k, j, i = np.nonzero(cranium.array)
    pick = np.random.default_rng(0).choice(len(i), size=min(3000, len(i)), replace=False)
    pts = (cta.ijk_to_centred @ np.stack((i[pick], j[pick], k[pick], np.ones(len(pick)))))[:3].T
    pts = pts - pts.mean(0)  # isocentre at the cranium's centre
    to_iso_mm = det.spacing_mm[0] * SOD_MM / SID_MM
    rows = []
    for primary in (0.0, -90.0, 90.0):
        angles = CArmAngles(primary, 0.0, SID_MM, SOD_MM)
        truth = torch.as_tensor(dicom_pixels(pts, angles, det.rows, det.cols, det.spacing_mm[0]))
        nominal = RigidTransform(torch.as_tensor(pose_from_carm_angles(angles))[None])
        p = torch.as_tensor(pts)[None]
        d0 = (project_points_tensor(nominal, det, p)[0][0] - truth).norm(dim=-1) * to_iso_mm
        r0, t0 = nominal.euler_zyx()
        r, t = r0.clone().requires_grad_(True), t0.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([r, t], max_iter=200, line_search_fn="strong_wolfe")

        def loss():
            opt.zero_grad()
            e = ((project_points_tensor(RigidTransform.from_euler_zyx(r, t), det, p)[0][0] - truth) ** 2).sum(-1).mean()
            e.backward()
            return e

        opt.step(loss)
        with torch.no_grad():
            d1 = (project_points_tensor(RigidTransform.from_euler_zyx(r, t), det, p)[0][0] - truth).norm(dim=-1) * to_iso_mm
            moved = float((RigidTransform.from_euler_zyx(r, t).matrix[0, :3, 3] - nominal.matrix[0, :3, 3]).norm())
        rows.append({
            "primary_deg": primary, "same_angles_rms_mm": float(d0.pow(2).mean().sqrt()), "same_angles_max_mm": float(d0.max()),
            "best_pose_rms_mm": float(d1.pow(2).mean().sqrt()), "best_pose_max_mm": float(d1.max()), "best_pose_source_shift_mm": moved,
        })
    return rows


def figure(path: Path, renders: dict, example) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(renders)
    fig, axes = plt.subplots(len(names) + 1, 3, figsize=(11, 3.9 * (len(names) + 1)))
    for row, name in enumerate(names):
        for col, v in enumerate(VIEWS):
            r, ax = renders[name][v], axes[row, col]
            ax.imshow(r["image"], cmap="gray")
            c, target = r["centre"], (r["anterior"] if v != C.VIEW_PA else r["right"])
            label = "face" if v != C.VIEW_PA else "patient's R"
            ax.annotate(label, xy=(target[1], target[0]), xytext=(c[1], c[0]), color="yellow", fontsize=11, ha="center",
                        arrowprops={"arrowstyle": "->", "color": "yellow", "lw": 2})
            ax.set_title(f"{name}: {C.VIEW_NAMES[v]} = {VIEW_WORDS[v]} (primary {VIEW_PRIMARY_DEG[v]:+.0f})", fontsize=10)
            ax.set_xticks([])
            ax.set_yticks([])
    ex = axes[-1]
    mask_side = face_side_of_lateral_cranium_mask(example["lat_registration_mask"] > 0.5)
    for ax, key, title in ((ex[0], "lat", "published LAT, primary {:.1f} (RAO)"), (ex[1], "pa", "published PA, primary {:.1f}")):
        img = example[f"{key}_registration_image"]
        ax.imshow(img, cmap="gray")
        ax.set_title(title.format(float(example[f"{key}_alpha_degrees"])), fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    h, w = example["lat_registration_image"].shape
    x_to = w * (0.92 if mask_side > 0 else 0.08)
    ex[0].annotate("face (teeth)", xy=(x_to, 0.9 * h), xytext=(w / 2, 0.6 * h), color="yellow", fontsize=11, ha="center",
                   arrowprops={"arrowstyle": "->", "color": "yellow", "lw": 2})
    ex[1].text(0.02 * w, 0.06 * h, "column 0: patient's R (DICOM)", color="yellow", fontsize=9)
    ex[2].axis("off")
    ex[2].text(0.0, 0.55, "Rows 1-2: our DRR at the isoposes; the\nDICOM angle each stands for under\n"
               "docs/conventions.md (section 7).\nRow 3: the GeoPose authors' real pair\n(MIT) as stored: row 0 superior.\n"
               "Its lateral (RAO) matches our LAT-,\nnot the published rule's LAT+.", fontsize=10, va="center")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def markdown_tables(result: dict) -> str:
    lines = ["| head | view | DICOM | anterior point | teeth | cranium floor |", "|---|---|---|---:|---:|---:|"]
    side = {1.0: "last columns", -1.0: "first columns", None: "-"}
    for r in result["face_side"]:
        lines.append(f"| {r['head']} | {r['view']} | {r['dicom']} | {side[r['anterior_point_side']]} | "
                     f"{side[r.get('teeth_side')]} | {side[r['cranium_floor_side']]} |")
    lines.append(f"| published example | lateral | primary {result['example']['lat_alpha_deg']:.1f} | - | - | "
                 f"{side[result['example']['cranium_floor_side']]} |")
    if result["diffdrr"]:
        lines += ["", "| head | view | NCC with DiffDRR | NCC with its mirror |", "|---|---|---:|---:|"]
        lines += [f"| {r['head']} | {r['view']} | {r['ncc']:.4f} | {r['ncc_mirrored']:.4f} |" for r in result["diffdrr"]]
    lines += ["", "| primary (deg) | same angles: RMS / max (mm) | best model pose: RMS / max (mm) | source moved (mm) |",
              "|---:|---:|---:|---:|"]
    lines += [f"| {r['primary_deg']:+.0f} | {r['same_angles_rms_mm']:.2f} / {r['same_angles_max_mm']:.2f} | "
              f"{r['best_pose_rms_mm']:.2f} / {r['best_pose_max_mm']:.2f} | {r['best_pose_source_shift_mm']:.1f} |"
              for r in result["approximation"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "docs")
    ap.add_argument("--px", type=int, default=128, help="render size (pixels across the model detector)")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    start = time.time()
    det = Detector.model().resized(args.px)
    example = np.load(SHARED / "geopose_example" / "sub-stroke0011_pre.npz", allow_pickle=False)
    renders, faces, diff = {}, [], []
    cases = heads()
    for name, (cta, labels, cranium) in cases.items():
        renders[name] = render_views(cta, cranium, det)
        faces += face_table(name, cta, labels, renders[name], det)
        diff += diffdrr_table(name, cta, Detector.model().resized(64))
    ge, _, ge_cranium = cases["GE head"]
    result = {
        "face_side": faces,
        "example": {"lat_alpha_deg": float(example["lat_alpha_degrees"]),
                    "cranium_floor_side": face_side_of_lateral_cranium_mask(example["lat_registration_mask"] > 0.5)},
        "diffdrr": diff,
        "approximation": approximation_table(ge, ge_cranium, Detector(256, 256, (1.2, 1.2), SID_MM)),
        "environment": {"torch": torch.__version__, "python": platform.python_version(), "machine": platform.machine(),
                        "diffdrr": _diffdrr_version()},
    }
    result["seconds"] = round(time.time() - start, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    figure(args.out / "conventions_isoposes.png", renders, example)
    (args.out / "conventions_check.json").write_text(json.dumps(result, indent=1) + "\n")
    print(markdown_tables(result))
    print(f"\n{result['seconds']} s; wrote {args.out / 'conventions_isoposes.png'} and {args.out / 'conventions_check.json'}")
    return 0


def _diffdrr_version() -> str | None:
    try:
        import diffdrr

        return diffdrr.__version__
    except ImportError:
        return None


if __name__ == "__main__":
    raise SystemExit(main())
