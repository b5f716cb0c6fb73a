"""Offscreen pictures of the MRML outputs for the README (regenerate with
``python -m geopose.mrml.screenshots --out docs``).

(a) ``slicer_{pa,lat}_{before,after}.png``: each view's DSA MAP node with the
projected vessel segmentation node drawn on it, at the nominal C-arm pose from
the DICOM angles ("before") and at the registered pose ("after").
(b) ``slicer_3d_view.png``: CTA vessel surfaces, both C-arm frustums and the MAP
planes, rendered with plain VTK (EGL/OSMesa offscreen) from the scene's nodes.

The phantom case comes from ``geopose.phantom``; the "registered" pose is what the
whole pipeline (shipped models, calibration, greedy Refine, 25 TTO steps) finds,
and each title gives its mPCD against the phantom's truth.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

import torch

from ..geometry import pose_from_carm_angles
from ..nets import make_predictors
from ..nets.manifest import verify_models
from ..phantom import labels as L
from ..phantom import make_subject
from ..phantom.dsa import sample_biplane, simulate_dsa
from ..register import RegistrationOptions, register_case
from ..register.evaluate import evaluate_pose
from ..resources import default_models_dir
from . import (
    camera_to_ras_points,
    frustum_model_node,
    labelmap_from_segmentation,
    new_scene,
    plane_volume_node,
    projected_segmentation_node,
    volume_from_node,
    volume_to_node,
)

#: Vessel segments shown: name -> (phantom artery labels, colour).
SEGMENTS = {
    "carotid (ICA)": ((L.ICA_LEFT, L.ICA_RIGHT), (0.95, 0.25, 0.2)),
    "anterior circulation": ((L.ANTERIOR_LEFT, L.ANTERIOR_RIGHT), (1.0, 0.75, 0.1)),
    "posterior circulation": ((L.POSTERIOR,), (0.3, 0.8, 1.0)),
}


def _segment_labels(labels) -> tuple[object, dict]:
    lab = np.zeros(labels.array.shape, np.uint8)
    segments = {}
    for n, (name, (values, color)) in enumerate(SEGMENTS.items(), start=1):
        all_values = list(values) + [v + L.INTRACRANIAL_OFFSET for v in values]
        lab[np.isin(labels.array, all_values)] = n
        segments[n] = (name, color)
    return labels.like(lab), segments


def build_case(seed: int = 3, spacing_mm: float = 2.0, matrix_px: int = 320):
    """A phantom scene: CTA, vessel labels, and per view the DSA MAP with projected
    vessels at the nominal pose (DICOM angles) and at the pose GeoPose registers
    with the shipped models. Returns (scene, dict of items)."""
    subject = make_subject(seed, spacing_mm=spacing_mm)
    rng = np.random.default_rng(seed)
    acqs, iso = sample_biplane(rng, subject)
    sims = {key: simulate_dsa(subject, a, a.pose(iso), rng, max_matrix_px=matrix_px) for key, a in zip(("pa", "lat"), acqs)}
    init, refine = make_predictors(verify_models(default_models_dir()), device="cpu")
    case = register_case(
        subject.cta, {k: s.run for k, s in sims.items()}, init=init, refine=refine,
        cranium_mask=subject.labels.like(L.cranium_mask(subject.labels.array).astype(np.uint8)),
        segmentation=subject.labels.like(L.vessel_mask(subject.labels.array).astype(np.uint8)),
        options=RegistrationOptions(device="cpu"),
    )
    carotid = np.concatenate([c["points_mm"] for c in subject.centerlines if c["name"].startswith("ica")])
    scene = new_scene()
    cta_node = volume_to_node(scene, subject.cta, "CTA")
    vessels, segments = _segment_labels(subject.labels)
    items = {"cta": cta_node, "vessels": vessels, "segments": segments, "views": {}}
    for key, acq in zip(("pa", "lat"), acqs):
        sim = sims[key]
        det = sim.run.detector
        poses = {"before": pose_from_carm_angles(acq.angles).matrix[0].numpy(), "after": case.views[key].final_pose[0].double().numpy()}
        view = {"detector": det}
        for when, pose in poses.items():
            pose_ras = subject.cta.centred_to_ras @ pose
            name = f"{acq.view_role} {when}"
            err = evaluate_pose(torch.as_tensor(pose), torch.as_tensor(sim.pose), det, acq.angles.sod_mm, carotid)
            view[when] = {
                "pose_ras": pose_ras,
                "mpcd_mm": err["mpcd_mm"],
                "map": plane_volume_node(scene, sim.map, det, pose_ras, f"GeoPose {name} MAP"),
                "projection": projected_segmentation_node(scene, vessels, segments, pose, det, f"GeoPose {name} projection"),
            }
        items["views"][acq.view_role] = view
    return scene, items


def slice_picture(map_node, projection_node, segments: dict, path: Path, title: str) -> Path:
    """The MAP node's image with each projected segment as a translucent colour (matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    image = volume_from_node(map_node).array[0].astype(float)
    lo, hi = np.percentile(image, (1, 99.5))
    rgb = np.repeat(((image - lo) / max(hi - lo, 1e-9)).clip(0, 1)[..., None], 3, axis=-1)
    for value, (name, color) in segments.items():
        lab, names = labelmap_from_segmentation(projection_node, map_node, [name])
        mask = lab.array[0] == names[name]
        rgb[mask] = 0.45 * rgb[mask] + 0.55 * np.asarray(color)
    fig, ax = plt.subplots(figsize=(4.2, 4.4), dpi=110)
    ax.imshow(rgb, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.axis("off")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for _n, c in segments.values()]
    ax.legend(handles, [n for n, _c in segments.values()], loc="lower center", fontsize=7, ncol=2, framealpha=0.8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def three_d_picture(scene, items: dict, path: Path, size: tuple[int, int] = (900, 700)) -> Path:
    """Vessel surfaces, C-arm frustums and MAP planes at the registered poses (plain VTK, offscreen)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import vtk
    from vtk.util import numpy_support

    from .scene import matrix_to_vtk
    from .volumes import image_data_from_array

    ren = vtk.vtkRenderer()
    ren.SetBackground(1.0, 1.0, 1.0)
    vessels = items["vessels"]
    image = image_data_from_array(vessels.array)
    for value, (_name, color) in items["segments"].items():
        surf = vtk.vtkDiscreteFlyingEdges3D()
        surf.SetInputData(image)
        surf.SetValue(0, value)
        xf = vtk.vtkTransformPolyDataFilter()
        t = vtk.vtkTransform()
        t.SetMatrix(matrix_to_vtk(vessels.ijk_to_ras))
        xf.SetTransform(t)
        xf.SetInputConnection(surf.GetOutputPort())
        smooth = vtk.vtkWindowedSincPolyDataFilter()
        smooth.SetInputConnection(xf.GetOutputPort())
        smooth.SetNumberOfIterations(15)
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputConnection(smooth.GetOutputPort())
        mapper.ScalarVisibilityOff()
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().SetColor(*color)
        ren.AddActor(actor)
    for role, color in (("PA", (0.2, 0.4, 0.85)), ("LAT", (0.1, 0.6, 0.3))):
        view = items["views"][role]
        after = view["after"]
        frustum = frustum_model_node(scene, after["pose_ras"], view["detector"], f"GeoPose {role} C-arm", color)
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputData(frustum.GetPolyData())
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().SetColor(*color)
        actor.GetProperty().SetLineWidth(2.0)
        ren.AddActor(actor)
        vol = volume_from_node(after["map"])
        arr = vol.array.astype(float)
        lo, hi = np.percentile(arr, (1, 99.5))
        gray = (255 * ((arr - lo) / max(hi - lo, 1e-9)).clip(0, 1)).astype(np.uint8)
        plane = image_data_from_array(gray)
        img_actor = vtk.vtkImageActor()
        img_actor.GetMapper().SetInputData(plane)
        img_actor.SetUserMatrix(matrix_to_vtk(vol.ijk_to_ras))
        img_actor.SetOpacity(0.85)
        ren.AddActor(img_actor)
        src = camera_to_ras_points(after["pose_ras"], view["detector"])["source"]
        sphere = vtk.vtkSphereSource()
        sphere.SetCenter(*src)
        sphere.SetRadius(15.0)
        m = vtk.vtkPolyDataMapper()
        m.SetInputConnection(sphere.GetOutputPort())
        a = vtk.vtkActor()
        a.SetMapper(m)
        a.GetProperty().SetColor(*color)
        ren.AddActor(a)
    centre = items["cta"].GetImageData() and volume_from_node(items["cta"]).centre_ras
    cam = ren.GetActiveCamera()
    cam.SetFocalPoint(*centre)
    cam.SetPosition(*(centre + np.array([1400.0, 1300.0, 900.0])))
    cam.SetViewUp(0, 0, 1)
    ren.ResetCamera()
    cam.Zoom(1.25)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.SetSize(*size)
    win.AddRenderer(ren)
    win.Render()
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(win)
    grab.Update()
    out = grab.GetOutput()
    w, h, _ = out.GetDimensions()
    pixels = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, -1)[::-1, :, :3]
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(pixels)).save(path)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Regenerate the Slicer-module pictures in docs/")
    parser.add_argument("--out", default="docs", help="output folder (default: docs)")
    parser.add_argument("--seed", type=int, default=3, help="phantom seed")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene, items = build_case(args.seed)
    for role, view in items["views"].items():
        for when, label in (("before", "nominal pose (DICOM angles)"), ("after", "registered pose")):
            v = view[when]
            slice_picture(v["map"], v["projection"], items["segments"], out / f"slicer_{role.lower()}_{when}.png",
                          f"{role} MAP + projected vessels: {label}\n(carotid mPCD {v['mpcd_mm']:.1f} mm)")
    three_d_picture(scene, items, out / "slicer_3d_view.png")
    print(f"pictures written to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
