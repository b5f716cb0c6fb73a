"""Validate our DRR renderer against DiffDRR 0.6.x on identical inputs.

Checks, each recorded in the JSON and the Markdown report:

1. density: our ``hu_to_density`` vs DiffDRR's ``transform_hu_to_density`` (same HU volume);
2. images: our renderer (several ``step_mm``) vs DiffDRR trilinear (default samples) and
   Siddon, at the three isoposes and random perturbations, on each detector size
   (global NCC, 13x13 patch NCC, relative L1, mean intensity ratio);
3. projected points: ``geopose.geometry.project_points_tensor`` vs DiffDRR's
   ``perspective_projection`` for fiducials inside the head (px);
4. bead centroid: a Gaussian bead's intensity centroid in our image vs DiffDRR's, and vs the
   projection of its centre (px);
5. gradients: our autograd pose gradient vs central finite differences (smooth volume),
   and vs DiffDRR's autograd gradient of the same loss (head phantom).

Usage (from the repository root, in the DiffDRR environment made by setup_diffdrr_env.sh)::

    .venv-diffdrr/bin/python benchmarks/compare_diffdrr.py --doc docs/renderer_validation.md
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import renderer_common as rc
from geopose.geometry import RigidTransform, project_points_tensor
from geopose.render import DRR, hu_to_density
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first

NCC_TARGET = 0.995
POINT_TOLERANCE_PX = 0.5


def check_density(volume) -> dict:
    ours = torch.as_tensor(hu_to_density(np.ascontiguousarray(volume.array, dtype=np.float32)))
    theirs = rc.DiffDRRAdapter(volume, rc.model_detector(8)).density_kji()
    return {"max_abs_difference": float((ours - theirs).abs().max())}


def compare_images(volume, sizes, steps, names, poses, device) -> list[dict]:
    rows = []
    for size in sizes:
        det = rc.model_detector(size)
        refs = {}
        with torch.no_grad():
            for renderer in ("trilinear", "siddon"):
                adapter = rc.DiffDRRAdapter(volume, det, renderer=renderer, device=device)
                refs[renderer] = torch.cat([adapter(poses[b]).cpu() for b in range(len(poses))])
            rows.append(_image_row(size, "DiffDRR trilinear", None, refs["trilinear"], refs, names))
            rows.append(_image_row(size, "DiffDRR Siddon", None, refs["siddon"], refs, names))
            for step in steps:
                ours = DRR.from_volume(volume, det, device=device, step_mm=step)
                img = torch.cat([ours(poses[b].to(device=device))[:, :1].cpu() for b in range(len(poses))])
                rows.append(_image_row(size, "ours trilinear", step, img, refs, names))
        print(f"  images {size}x{size}: done")
    return rows


def _image_row(size, renderer, step, img, refs, names) -> dict:
    per_pose = []
    for b, name in enumerate(names):
        a = img[b, 0]
        per_pose.append(
            {
                "pose": name,
                "ncc_vs_trilinear": rc.ncc(a, refs["trilinear"][b, 0]),
                "ncc_vs_siddon": rc.ncc(a, refs["siddon"][b, 0]),
                "patch_ncc_vs_trilinear": rc.patch_ncc(a, refs["trilinear"][b, 0]),
                "rel_l1_vs_trilinear": rc.relative_l1(a, refs["trilinear"][b, 0]),
                "mean_ratio_vs_siddon": float(a.double().mean() / refs["siddon"][b, 0].double().mean()),
            }
        )
    return {"size": size, "renderer": renderer, "step_mm": step, "per_pose": per_pose}


def compare_points(volume, names, poses, n_points: int = 40, seed: int = 0) -> dict:
    """Fiducials: random points within +-80 mm of the centre; max pixel distance over poses."""
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n_points, 3, generator=g, dtype=torch.float64) - 0.5) * 160.0
    out = {}
    for size in (128, 256):
        det = rc.model_detector(size)
        adapter = rc.DiffDRRAdapter(volume, det)
        ours, _ = project_points_tensor(poses, det, pts.expand(len(poses), -1, -1))
        theirs = adapter.project(poses, pts.expand(len(poses), -1, -1)).double()
        err = (ours - theirs).norm(dim=-1)
        out[f"{size}"] = {"max_px": float(err.max()), "mean_px": float(err.mean()), "n_points": n_points * len(poses)}
    return out


def compare_bead(names, poses, device) -> list[dict]:
    """Centroid of a single-bead volume: ours vs DiffDRR (trilinear, Siddon) vs the projected centre."""
    vol = rc.bead_volume()
    centre = torch.tensor(vol.metadata["centre_mm"], dtype=torch.float64)
    det = rc.model_detector(256)
    ours = DRR.from_volume(vol, det, device=device)
    tri = rc.DiffDRRAdapter(vol, det, renderer="trilinear", device=device)
    sid = rc.DiffDRRAdapter(vol, det, renderer="siddon", device=device)
    rows = []
    with torch.no_grad():
        for b, name in enumerate(names):
            pose = poses[b]
            proj, _ = project_points_tensor(pose, det, centre[None])
            proj = proj[0, 0].tolist()
            c = {}
            for key, img in (("ours", ours(pose.to(device=device))), ("trilinear", tri(pose)), ("siddon", sid(pose))):
                im = img[0, 0].cpu()
                c[key] = rc.intensity_centroid(im - im.min())
            rows.append(
                {
                    "pose": name,
                    "projected_centre": proj,
                    "centroid_ours": c["ours"],
                    "ours_vs_trilinear_px": float(np.hypot(*np.subtract(c["ours"], c["trilinear"]))),
                    "ours_vs_siddon_px": float(np.hypot(*np.subtract(c["ours"], c["siddon"]))),
                    "ours_vs_projection_px": float(np.hypot(*np.subtract(c["ours"], proj))),
                    "trilinear_vs_projection_px": float(np.hypot(*np.subtract(c["trilinear"], proj))),
                }
            )
    return rows


def gradient_vs_finite_differences(poses, names, step_fractions=(0.5, 0.125)) -> list[dict]:
    """Our autograd pose gradient vs central differences, smooth 32^3 volume (4 mm voxels),
    64x64 detector, at ray steps of ``step_fractions`` x the voxel size."""
    vol = rc.smooth_blobs()
    det = rc.model_detector(64)
    rows = []
    for frac in step_fractions:
        drr = DRR.from_volume(vol, det, step_mm=frac * min(vol.spacing_mm))
        for b in range(len(poses)):
            r0, t0 = (x.float() for x in poses[b].euler_zyx())
            weights = torch.randn(det.shape, generator=torch.Generator().manual_seed(b))
            with torch.no_grad():
                target = drr(RigidTransform.from_euler_zyx(r0 + 0.03, t0 + 3.0))[0, 0]

            def render(r, t):
                return drr(RigidTransform.from_euler_zyx(r, t))[0, 0]

            out = {"pose": names[b], "step_mm": drr.step_mm}
            for loss_name, loss in (
                ("weighted sum", lambda img: (img * weights).mean()),
                ("-NCC", lambda img: _neg_ncc(img, target)),
            ):
                auto, fd = rc.autograd_and_fd_gradients(render, loss, r0, t0, h_rad=1e-3, h_mm=0.1)
                out[loss_name] = {
                    "autograd": auto.tolist(),
                    "finite_difference": fd.tolist(),
                    "relative_error": float((auto - fd).norm() / fd.norm()),
                    "cosine": float(torch.nn.functional.cosine_similarity(auto, fd, dim=0)),
                }
            rows.append(out)
    return rows


def _neg_ncc(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a = (a - a.mean()) / a.std(correction=0)
    b = (b - b.mean()) / b.std(correction=0)
    return -(a * b).mean()


def gradient_vs_diffdrr(volume, poses, names, step_mm: float, device) -> list[dict]:
    """d(-NCC to a target at a nearby pose)/d(r, t): our autograd vs DiffDRR's autograd, 128x128."""
    det = rc.model_detector(128)
    ours = DRR.from_volume(volume, det, device=device, step_mm=step_mm)
    theirs = rc.DiffDRRAdapter(volume, det, device=device)
    rows = []
    for b in range(len(poses)):
        r0, t0 = (x.float().to(device) for x in poses[b].euler_zyx())
        with torch.no_grad():
            target = theirs.render_params(r0 + 0.02, t0 + 2.0)[0, 0]
        grads = {}
        for key, render in (
            ("ours", lambda r, t: ours(RigidTransform.from_euler_zyx(r, t))[0, 0]),
            ("diffdrr", lambda r, t: theirs.render_params(r, t)[0, 0]),
        ):
            r = r0.clone().requires_grad_(True)
            t = t0.clone().requires_grad_(True)
            _neg_ncc(render(r, t), target).backward()
            grads[key] = torch.cat((r.grad[0], t.grad[0])).double().cpu()
        rows.append(
            {
                "pose": names[b],
                "ours": grads["ours"].tolist(),
                "diffdrr": grads["diffdrr"].tolist(),
                "relative_difference": float((grads["ours"] - grads["diffdrr"]).norm() / grads["diffdrr"].norm()),
                "cosine": float(torch.nn.functional.cosine_similarity(grads["ours"], grads["diffdrr"], dim=0)),
            }
        )
    return rows


def save_figure(volume, names, poses, path: Path, device) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    det = rc.model_detector(256)
    ours = DRR.from_volume(volume, det, device=device)
    tri = rc.DiffDRRAdapter(volume, det, device=device)
    picks = [1, 2]  # PA and LAT+ isoposes
    fig, axes = plt.subplots(len(picks), 3, figsize=(10.5, 3.6 * len(picks)))
    with torch.no_grad():
        for row, b in enumerate(picks):
            a = ours(poses[b].to(device=device))[0, 0].cpu()
            d = tri(poses[b])[0, 0].cpu()
            for ax, im, title in ((axes[row, 0], a, "ours"), (axes[row, 1], d, "DiffDRR trilinear")):
                ax.imshow(im, cmap="gray")
                ax.set_title(f"{names[b]}: {title}")
            diff = (a - d).numpy()
            lim = float(np.abs(diff).max())
            h = axes[row, 2].imshow(diff, cmap="RdBu", vmin=-lim, vmax=lim)
            axes[row, 2].set_title("ours - DiffDRR (density x mm)")
            fig.colorbar(h, ax=axes[row, 2], fraction=0.046)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def summarise(result: dict) -> str:
    """Markdown tables of the recorded result."""
    L = [
        f"Run: torch {result['torch']}, DiffDRR {result['diffdrr']}, device `{result['device']}`, "
        f"{result['threads']} threads; volume: {result['volume']}; {len(result['poses'])} poses "
        f"({', '.join(result['poses'])}); {result['seconds']:.0f} s.",
        "",
        f"**Density.** max |ours - DiffDRR| = {result['density']['max_abs_difference']:.3g} (densities in [0, 1]).",
        "",
        "**Images** (worst pose / mean over poses; NCC target >= "
        f"{NCC_TARGET}):",
        "",
        "| detector | renderer | step mm | NCC vs DiffDRR tri (min / mean) | NCC vs DiffDRR Siddon (min) "
        "| patch NCC vs tri (min) | rel. L1 vs tri (max) | mean / Siddon mean |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in result["images"]:
        pp = row["per_pose"]

        def col(key, fn):
            return fn(p[key] for p in pp)

        L.append(
            f"| {row['size']}x{row['size']} | {row['renderer']} | {row['step_mm'] if row['step_mm'] else '-'} "
            f"| {col('ncc_vs_trilinear', min):.5f} / {np.mean([p['ncc_vs_trilinear'] for p in pp]):.5f} "
            f"| {col('ncc_vs_siddon', min):.5f} | {col('patch_ncc_vs_trilinear', min):.4f} "
            f"| {col('rel_l1_vs_trilinear', max):.4f} "
            f"| {min(p['mean_ratio_vs_siddon'] for p in pp):.4f}..{max(p['mean_ratio_vs_siddon'] for p in pp):.4f} |"
        )
    L += [
        "",
        f"**Projected points** (tolerance {POINT_TOLERANCE_PX} px; DiffDRR's pixel-corner origin shifted by "
        f"{rc.DiffDRRAdapter.PIXEL_CENTRE_OFFSET} px to our pixel centres):",
        "",
        "| detector | points | max px | mean px |",
        "|---|---:|---:|---:|",
    ]
    for size, v in result["points"].items():
        L.append(f"| {size}x{size} | {v['n_points']} | {v['max_px']:.2e} | {v['mean_px']:.2e} |")
    L += [
        "",
        "**Bead centroid** (256x256, default step; intensity-weighted centroids, px):",
        "",
        "| pose | ours vs DiffDRR tri | ours vs DiffDRR Siddon | ours vs projected centre | DiffDRR tri vs projected centre |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in result["bead"]:
        L.append(
            f"| {r['pose']} | {r['ours_vs_trilinear_px']:.4f} | {r['ours_vs_siddon_px']:.4f} "
            f"| {r['ours_vs_projection_px']:.4f} | {r['trilinear_vs_projection_px']:.4f} |"
        )
    L += [
        "",
        "**Gradient vs central finite differences** (ours, smooth tapered 32^3 volume with 4 mm voxels, "
        "64x64 detector, h = 1e-3 rad / 0.1 mm; relative error = |g_auto - g_fd| / |g_fd| over the 6 pose "
        "parameters; weighted-sum loss = mean of the image times fixed Gaussian weights):",
        "",
        "| step mm | pose | weighted-sum loss: rel. error | cosine | -NCC loss: rel. error | cosine |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for r in result["gradient_fd"]:
        a, b = r["weighted sum"], r["-NCC"]
        L.append(
            f"| {r['step_mm']:g} | {r['pose']} | {a['relative_error']:.2e} | {a['cosine']:.6f} "
            f"| {b['relative_error']:.2e} | {b['cosine']:.6f} |"
        )
    L += [
        "",
        f"**Gradient vs DiffDRR's autograd** (head phantom, 128x128, ours at step {result['gradient_step_mm']} mm, "
        "loss -NCC to a DiffDRR image at a pose 0.02 rad / 2 mm away):",
        "",
        "| pose | relative difference | cosine |",
        "|---|---:|---:|",
    ]
    for r in result["gradient_diffdrr"]:
        L.append(f"| {r['pose']} | {r['relative_difference']:.3f} | {r['cosine']:.5f} |")
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--volume", choices=["phantom", "headsq"], default="phantom")
    p.add_argument("--volume-size", type=int, default=256)
    p.add_argument("--sizes", type=int, nargs="+", default=[128, 256], help="detector sizes (px)")
    p.add_argument("--steps", type=float, nargs="+", default=[0.45, 0.9, 1.35, 1.8, 2.7], help="our step_mm values")
    p.add_argument("--n-random", type=int, default=5, help="random poses besides the three isoposes")
    p.add_argument("--gradient-step", type=float, default=0.9, help="our step_mm in the DiffDRR gradient comparison")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--doc", type=Path, default=None, help="report file: the section between <!-- validation:VOLUME --> markers is replaced; JSON beside it")
    p.add_argument("--figure", type=Path, default=None, help="PNG of ours vs DiffDRR at PA and LAT+")
    args = p.parse_args(argv)
    if rc.diffdrr_version() is None:
        raise SystemExit("DiffDRR is not importable here: run benchmarks/setup_diffdrr_env.sh and use .venv-diffdrr/bin/python")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    t_start = time.perf_counter()
    volume = rc.head_phantom(args.volume_size) if args.volume == "phantom" else rc.headsq_volume(args.volume_size)
    names, poses = rc.validation_poses(args.n_random)
    result = {
        "torch": torch.__version__,
        "diffdrr": rc.diffdrr_version(),
        "device": str(device),
        "threads": torch.get_num_threads(),
        "volume": f"{volume.metadata['name']} ({args.volume_size}^3, {volume.spacing_mm[0]:.3g} mm voxels)",
        "poses": names,
        "pose_params": [[*r, *t] for r, t in zip(*(x.tolist() for x in poses.euler_zyx()))],
        "gradient_step_mm": args.gradient_step,
    }
    result["density"] = check_density(volume)
    print("density:", result["density"])
    result["points"] = compare_points(volume, names, poses)
    print("points:", result["points"])
    result["bead"] = compare_bead(names, poses, device)
    print("bead: max ours-vs-tri", max(r["ours_vs_trilinear_px"] for r in result["bead"]))
    result["gradient_fd"] = gradient_vs_finite_differences(poses, names)
    print("gradient fd: max rel error", max(r["-NCC"]["relative_error"] for r in result["gradient_fd"]))
    result["gradient_diffdrr"] = gradient_vs_diffdrr(volume, poses, names, args.gradient_step, device)
    print("gradient vs DiffDRR: min cosine", min(r["cosine"] for r in result["gradient_diffdrr"]))
    result["images"] = compare_images(volume, args.sizes, args.steps, names, poses, device)
    result["seconds"] = time.perf_counter() - t_start
    result["load_average_1_5_15"] = list(os.getloadavg())
    table = summarise(result)
    print(table)
    if args.figure is not None:
        save_figure(volume, names, poses, args.figure, device)
    if args.doc is not None:
        from bench_renderer import update_doc

        update_doc(args.doc, f"validation:{args.volume}", table)
        js = args.doc.with_name(f"{args.doc.stem}_{args.volume}.json")
        js.write_text(json.dumps(result, indent=2) + "\n")
        print(f"updated {args.doc} and wrote {js}")


if __name__ == "__main__":
    main()
