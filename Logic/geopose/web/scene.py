"""The MRML scene the page's 3D view shows for a :class:`~.session.Review`, or for the networks' estimate while
the registration runs on, built with the :mod:`geopose.mrml` adapters: the CTA (volume rendering), per view the
pose transform, the C-arm frustum, the DSA MAP as a texture on its detector plane and as a plane volume (what a
saved scene keeps), and saving the scene (.mrb) and the transforms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import mrml
from ..errors import InputError
from ..geometry.frames import pose_to_patient

__all__ = ["VIEW_COLOURS", "VR_PRESET", "show_estimate", "show_review", "save_scene", "save_transforms"]

#: Frustum colour per view key (rgb 0-1).
VIEW_COLOURS = {"pa": (0.25, 0.55, 1.0), "lat": (0.2, 0.85, 0.35)}
#: Volume-rendering preset of the CTA (Slicer's presets): bone and contrast-filled vessels.
VR_PRESET = "CT-Chest-Contrast-Enhanced"


def show_review(slicer_app, review, keep_camera: bool = False) -> dict:
    """Replace the scene's contents with ``review``'s nodes; returns them by name (``cta``, ``<key>Pose``,
    ``<key>Frustum``, ``<key>Image``, ``<key>MAP``). ``keep_camera``: the scene showed the same registration's
    estimate (:func:`show_estimate`), so the camera stays where the user may have moved it."""
    views = {key: (view.get("role", key.upper()), np.asarray(view["pose_ras"], dtype=float))
             for key, view in review.record["views"].items()}
    return _show(slicer_app, review.cta, views, review.maps, review.detectors, keep_camera)


def show_estimate(slicer_app, estimate, maps: dict[str, np.ndarray]) -> dict:
    """Replace the scene's contents with the nodes of the networks' estimate of a registration still running
    (``estimate``: a :class:`~geopose.register.cli.FileEstimate`; ``maps``: each run's MAP), named as
    :func:`show_review` names them with "(estimate)" in the titles."""
    cta = estimate.cta
    views = {key: (f"{run.view_role} (estimate)", pose_to_patient(estimate.preliminary.poses[key], cta.ijk_to_ras, cta.shape_ijk))
             for key, run in estimate.runs.items()}
    return _show(slicer_app, cta, views, maps, {key: run.detector for key, run in estimate.runs.items()}, False)


def _show(slicer_app, cta, views: dict[str, tuple[str, np.ndarray]], maps: dict[str, np.ndarray], detectors: dict,
          keep_camera: bool) -> dict:
    """The scene of the CTA and, per view key, its title and camera-to-RAS pose (mm), MAP and detector; the camera
    placed to show them unless ``keep_camera``."""
    scene = slicer_app.scene
    for cls in ("vtkMRMLScalarVolumeNode", "vtkMRMLModelNode", "vtkMRMLLinearTransformNode"):
        for node in list(scene.GetNodesByClass(cls)):
            scene.RemoveNode(node)
    nodes = {"cta": mrml.volume_to_node(scene, cta, "CTA")}
    nodes["cta"].CreateDefaultDisplayNodes()
    slicer_app.display_manager.show_volume(nodes["cta"], vr_preset=VR_PRESET)
    for key, (title, pose_ras) in views.items():
        det = detectors[key]
        nodes[f"{key}Pose"] = mrml.pose_transform_node(scene, pose_ras, f"GeoPose {title} pose")
        nodes[f"{key}Frustum"] = mrml.frustum_model_node(scene, pose_ras, det, f"GeoPose {title} C-arm", VIEW_COLOURS.get(key, (1, 1, 0)))
        nodes[f"{key}Image"] = mrml.detector_image_model_node(scene, maps[key], det, pose_ras, f"GeoPose {title} DSA on detector")
        nodes[f"{key}MAP"] = mrml.plane_volume_node(scene, maps[key], det, pose_ras, f"GeoPose {title} MAP")
        nodes[f"{key}MAP"].GetDisplayNode().SetVisibility(False)
    for view in slicer_app.view_manager.get_threed_views():
        if not keep_camera:
            view.reset_camera()
            view.renderer().GetActiveCamera().Elevation(20)
            view.renderer().GetActiveCamera().Azimuth(35)
            view.renderer().ResetCamera()
        view.schedule_render()
    return nodes


def save_scene(slicer_app, folder: Path) -> Path:
    """The whole scene as ``folder/geopose_scene.mrb``."""
    if not list(slicer_app.scene.GetNodesByClass("vtkMRMLLinearTransformNode")):
        raise InputError("there is no result to save yet: register a case or open a result folder first")
    return mrml.save_mrb(slicer_app.scene, Path(folder) / "geopose_scene.mrb")


def save_transforms(slicer_app, folder: Path) -> list[Path]:
    """Each pose transform (camera-to-RAS, mm) as ``folder/<node name>.h5`` (ITK transform files Slicer reads)."""
    import slicer

    nodes = list(slicer_app.scene.GetNodesByClass("vtkMRMLLinearTransformNode"))
    if not nodes:
        raise InputError("there is no result to save yet: register a case or open a result folder first")
    written = []
    for node in nodes:
        path = Path(folder) / (node.GetName().replace(" ", "_") + ".h5")
        storage = slicer.vtkMRMLTransformStorageNode()
        storage.SetFileName(str(path))
        if not storage.WriteData(node):
            raise OSError(f"could not write {path}: check the folder is writable")
        written.append(path)
    return written
