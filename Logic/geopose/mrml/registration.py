"""A registration's nodes: its inputs read from a scene and its result written to one.

Inputs (:func:`read_inputs`): the CTA volume node, each DSA run (a sequence or multi-frame volume
node with its ``GeoPose.*`` geometry attributes, :func:`run_from_node`), the optional vessel
segmentation and cranium mask on the CTA grid. Outputs (:func:`result_nodes`): per view key
(``pa``, ``lat``) the pose transform (camera-to-RAS), camera, C-arm frustum, the run on its
registered detector plane, the MAP and the projected segmentation, and one results table
(:func:`result_rows`); the same nodes at the networks' estimate while the registration goes on
(:func:`preliminary_nodes`). :func:`register_nodes` does these steps around ``register_case``. Node roles for a front end's selectors: :func:`is_dsa_image`,
:func:`dsa_image_ids`, :func:`first_cta_candidate`. The Slicer module (``GeoPoseModule``) is a
panel over these; they run in plain Python with the ``slicer-core`` wheel as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from ..dsa import DSARun
from ..errors import InputError
from ..geometry.frames import pose_to_patient
from ..geometry.poses import pose_from_carm_angles
from ..register.case import VIEW_KEYS
from ..volume import Volume
from .outputs import camera_node, frustum_model_node, pose_transform_node, projected_segmentation_node, result_table_node
from .plane import dsa_sequence_node, frames_from_node, geometry_from_attributes, plane_volume_node, proxy_sequence, set_geometry_attributes
from .volumes import labelmap_from_segmentation, segment_colors, volume_from_node

__all__ = [
    "VIEW_KEYS", "VIEW_TITLES", "OUTPUT_KEYS", "RegistrationInputs", "is_dsa_image", "dsa_image_ids",
    "first_cta_candidate", "geometry_overrides", "run_from_node", "read_dsa_node", "segmentation_labels",
    "read_inputs", "result_rows", "preliminary_nodes", "result_nodes", "result_summary", "register_nodes",
    "RESULT_ATTRIBUTE", "PRELIMINARY_RESULT", "FINAL_RESULT",
]

VIEW_TITLES = {"pa": "PA", "lat": "LAT"}
#: Output node key suffixes per view: ``paPose``, ``latMAP``, ... (``DSABrowser``: the DSA sequence's browser).
OUTPUT_KEYS = ("Pose", "Camera", "Frustum", "DSA", "DSABrowser", "MAP", "Projection")


@dataclass
class RegistrationInputs:
    """What :func:`read_inputs` read: the CTA (HU), the runs by view key, the segmentation as a label map
    on the CTA grid with ``{label value: (segment name, rgb)}``, and the cranium mask (both optional)."""

    cta: Volume
    runs: dict[str, DSARun]
    labels: Volume | None = None
    segments: dict[int, tuple[str, tuple[float, float, float]]] = field(default_factory=dict)
    cranium: Volume | None = None


# ------------------------------------------------------------------ node roles
def _volume_nodes(scene) -> list:
    cls = "vtkMRMLScalarVolumeNode"
    return [scene.GetNthNodeByClass(n, cls) for n in range(scene.GetNumberOfNodesByClass(cls))]


def is_dsa_image(node) -> bool:
    """Whether a volume node is a DSA image (a detector-plane volume with GeoPose geometry, or a sequence's shown frame)."""
    return geometry_from_attributes(node)[0] is not None or proxy_sequence(node) is not None


def dsa_image_ids(scene) -> list[str]:
    """IDs of the scalar volumes of ``scene`` that are DSA images (never a CTA)."""
    return [node.GetID() for node in _volume_nodes(scene) if is_dsa_image(node)]


def first_cta_candidate(scene):
    """The first scalar volume of ``scene`` that is not a DSA image (label maps excluded), or None."""
    return next((node for node in _volume_nodes(scene)
                 if node.GetClassName() == "vtkMRMLScalarVolumeNode" and not is_dsa_image(node)), None)


# ------------------------------------------------------------------ inputs
def geometry_overrides(values: Mapping[str, float]) -> dict[str, Any]:
    """Overrides for :func:`run_from_node` / ``read_dsa`` from a panel's geometry fields
    (``primary_deg``, ``secondary_deg``, ``sid_mm``, ``sod_mm``, ``pixel_spacing_mm``): angles as given,
    a distance or spacing of 0 keeps the file's value, one pixel spacing is square pixels."""
    out = {k: float(v) for k, v in values.items() if k.endswith("_deg") or v > 0}
    if "pixel_spacing_mm" in out:
        out["pixel_spacing_mm"] = (out["pixel_spacing_mm"], out["pixel_spacing_mm"])
    return out


#: Attribute of a DSA sequence node read from a native run: how it was subtracted (``geopose.dsa.subtraction``).
SUBTRACTION_ATTRIBUTE = "GeoPose.subtraction"


def run_from_node(node, overrides: Mapping[str, Any] | None = None) -> DSARun:
    """A :class:`~geopose.dsa.DSARun` from a sequence / multi-frame volume node, its ``GeoPose.*``
    geometry attributes and ``overrides`` (``geopose.dsa`` key names, mm / deg), through the checks the
    file readers apply (``geopose.dsa.run_from_geometry``). A run's shown frame stands for its sequence."""
    from ..dsa import run_from_geometry

    node = proxy_sequence(node) or node
    detector, angles, frame_time = geometry_from_attributes(node)
    geometry: dict[str, Any] = {}
    if detector is not None:
        geometry.update(sid_mm=detector.sdd_mm, pixel_spacing_mm=detector.spacing_mm,
                        principal_offset_mm=detector.principal_offset_mm)
    if angles is not None:
        geometry.update(primary_deg=angles.primary_deg, secondary_deg=angles.secondary_deg,
                        sid_mm=angles.sid_mm, sod_mm=angles.sod_mm)
    if frame_time:
        geometry["frame_time_ms"] = frame_time * 1000.0
    geometry.update(overrides or {})
    name = node.GetName()
    subtraction = node.GetAttribute(SUBTRACTION_ATTRIBUTE)  # a native run, subtracted when it was read
    return run_from_geometry(frames_from_node(node), geometry, name=f"DSA node {name!r}", source=f"Slicer node {name}",
                             metadata={"subtraction": subtraction} if subtraction else None)


def _frame_time_s(run: DSARun) -> float | None:
    return run.frame_time_ms / 1000.0 if run.frame_time_ms else None


def read_dsa_node(scene, path, name: str, reference=None, **overrides):
    """Read a DSA run (DICOM XA, or NIfTI + JSON sidecar; ``overrides`` as ``read_dsa`` takes them) into a
    sequence node ``name`` with a browser, on its nominal detector plane: the pose of its C-arm angles
    about the grid centre of the volume node ``reference`` (the CTA; RAS origin without one)."""
    from ..dsa import read_dsa

    run = read_dsa(path, **overrides)
    pose = pose_from_carm_angles(run.angles)
    if reference is not None:
        pose = volume_from_node(reference).centred_to_ras @ pose
    seq, browser = dsa_sequence_node(scene, run.frames, run.detector, pose, name, frame_time_s=_frame_time_s(run),
                                     angles=run.angles)
    if "subtraction" in run.metadata:
        seq.SetAttribute(SUBTRACTION_ATTRIBUTE, run.metadata["subtraction"])
    return seq, browser


def segmentation_labels(segmentation, reference) -> tuple[Volume | None, dict]:
    """``(label map on reference's grid, {value: (segment name, rgb)})`` of a segmentation node, or ``(None, {})``."""
    if segmentation is None:
        return None, {}
    labels, values = labelmap_from_segmentation(segmentation, reference)
    colors = segment_colors(segmentation)
    return labels, {value: (name, colors[name]) for name, value in values.items()}


def read_inputs(cta, dsa_pa, dsa_lat, segmentation=None, cranium_mask=None, overrides: Mapping[str, Mapping] | None = None,
                outputs: Mapping[str, Any] | None = None, tick: Callable[[], None] | None = None) -> RegistrationInputs:
    """The registration inputs of the nodes, checked: each given, the CTA no DSA image, no input node among
    ``outputs`` (output nodes by key, :data:`OUTPUT_KEYS`). ``overrides``: per view key, as :func:`run_from_node`
    takes them; ``tick()`` is called between the reads (e.g. to process GUI events). Nodes are not modified."""
    if cta is None or dsa_pa is None or dsa_lat is None:
        raise InputError("select a CTA volume and a PA and a lateral DSA run")
    inputs = [n for n in (cta, dsa_pa, dsa_lat, segmentation, cranium_mask) if n is not None]
    for key, node in (outputs or {}).items():
        if any(node is n for n in inputs):
            raise InputError(f"output {key} is the input node {node.GetName()!r}: choose another output node, "
                             "inputs are never overwritten")
    if is_dsa_image(cta):
        raise InputError(f"the CTA {cta.GetName()!r} is a DSA image (a detector plane or a run's shown frame): "
                         "choose the head CTA volume")
    tick = tick or (lambda: None)
    volume = volume_from_node(cta)
    tick()
    overrides = overrides or {}
    runs = {key: run_from_node(node, overrides.get(key)) for key, node in zip(VIEW_KEYS, (dsa_pa, dsa_lat))}
    tick()
    labels, segments = segmentation_labels(segmentation, cta)
    cranium = segmentation_labels(cranium_mask, cta)[0]
    tick()
    return RegistrationInputs(volume, runs, labels, segments, cranium)


# ------------------------------------------------------------------ outputs
def _matrix(pose) -> np.ndarray:
    return np.asarray(pose, dtype=float).reshape(4, 4)


def result_rows(result, runs: Mapping[str, DSARun]) -> list[dict[str, Any]]:
    """The results table, one row per view (``{column: value}``, numbers as floats): mNCC, silhouette Dice,
    quality flag and reasons, the registration's mode and starts, the view's pixel axes (DICOM
    PatientOrientation letters, docs/conventions.md section 7) for the registered pose and for the run's own
    angles (they differ when the image is mirrored or the side wrong), each stage's distance to the final
    pose (mm), the runtimes, the engine and the notes. Reads ``result.views[key]`` (``final_pose``,
    ``stage_poses``, ``final_mncc``, ``silhouette_dice``, ``quality``), ``result.registration``,
    ``result.runtimes_s``, ``result.engine`` and ``result.notes``."""
    from ..register.record import patient_orientation

    rows = []
    for key in VIEW_KEYS:
        view, final = result.views[key], _matrix(result.views[key].final_pose)
        row: dict[str, Any] = {
            "view": VIEW_TITLES[key], "mNCC": float(view.final_mncc), "silhouette Dice": float(view.silhouette_dice),
            "quality": view.quality.flag, "reasons": "; ".join(view.quality.reasons),
            "registration": result.registration.mode, "Refine start": result.registration.refine_start,
            "TTO start": result.registration.chosen_start,
            "pixel axes (registered)": "\\".join(patient_orientation(final)),
            "pixel axes (DICOM angles)": "\\".join(patient_orientation(pose_from_carm_angles(runs[key].angles))),
        }
        for stage, pose in view.stage_poses.items():
            row[f"{stage} to final (mm)"] = float(math.dist(_matrix(pose)[:3, 3], final[:3, 3]))
        row.update({f"runtime {stage} (s)": float(t) for stage, t in result.runtimes_s.items()})
        row["device"] = f"{result.engine['backend']} on {result.engine['device']}"
        row["notes"] = "; ".join(result.notes)
        rows.append(row)
    return rows


#: Attribute of each view's pose transform node: which result it holds (:data:`PRELIMINARY_RESULT`, :data:`FINAL_RESULT`).
RESULT_ATTRIBUTE = "GeoPose.result"
PRELIMINARY_RESULT = "networks' estimate (preliminary: the test-time optimisation is running)"
FINAL_RESULT = "final"


def _view_nodes(scene, inputs: RegistrationInputs, key: str, pose, given: Mapping[str, Any], out: dict[str, Any],
                which: str, prepared_map: np.ndarray | None = None) -> None:
    """Into ``out``: view ``key``'s pose transform (its :data:`RESULT_ATTRIBUTE` set to ``which``), camera, C-arm,
    the run on its detector plane, the projected segmentation (with a segmentation) and, given ``prepared_map``, the
    MAP, all placed at ``pose`` (camera-to-world, centred native CTA frame, mm); ``given`` nodes are updated in place."""
    run, title, cta = inputs.runs[key], VIEW_TITLES[key], inputs.cta
    pose = _matrix(pose)
    pose_ras = pose_to_patient(pose, cta.ijk_to_ras, cta.shape_ijk)
    det, name = run.detector, f"GeoPose {title}"
    out[f"{key}Pose"] = pose_transform_node(scene, pose_ras, f"{name} pose", node=given.get(f"{key}Pose"))
    out[f"{key}Pose"].SetAttribute(RESULT_ATTRIBUTE, which)
    out[f"{key}Camera"] = camera_node(scene, pose_ras, det, f"{name} camera", node=given.get(f"{key}Camera"))
    out[f"{key}Frustum"] = frustum_model_node(scene, pose_ras, det, f"{name} C-arm", node=given.get(f"{key}Frustum"))
    out[f"{key}DSA"], out[f"{key}DSABrowser"] = dsa_sequence_node(
        scene, run.frames, det, pose_ras, f"{name} DSA", frame_time_s=_frame_time_s(run), angles=run.angles,
        node=given.get(f"{key}DSA"))
    if prepared_map is not None:
        out[f"{key}MAP"] = plane_volume_node(scene, prepared_map, det, pose_ras, f"{name} MAP", node=given.get(f"{key}MAP"))
        set_geometry_attributes(out[f"{key}MAP"], det, run.angles, _frame_time_s(run))
    if inputs.labels is not None and inputs.segments:
        out[f"{key}Projection"] = projected_segmentation_node(
            scene, inputs.labels, inputs.segments, pose, det, f"{name} projected segmentation",
            node=given.get(f"{key}Projection"))


def preliminary_nodes(scene, inputs: RegistrationInputs, preliminary, outputs: Mapping[str, Any] | None = None,
                      tick: Callable[[], None] | None = None) -> dict[str, Any]:
    """The nodes of a result the registration reached before its end (``preliminary``: a
    ``geopose.register.progress.Preliminary``), so that the user sees it meanwhile: per view the pose transform,
    camera, C-arm, run and projected segmentation of :func:`result_nodes` (not the MAP or the table), the pose
    transform's :data:`RESULT_ATTRIBUTE` saying it is preliminary. ``outputs``: existing nodes, updated in place;
    pass the returned ones to :func:`result_nodes`, which moves them to the final result."""
    given, out = dict(outputs or {}), dict(outputs or {})
    for key in VIEW_KEYS:
        _view_nodes(scene, inputs, key, preliminary.poses[key], given, out, PRELIMINARY_RESULT)
        if tick is not None:
            tick()
    return out


def result_nodes(scene, inputs: RegistrationInputs, result, outputs: Mapping[str, Any] | None = None,
                 tick: Callable[[], None] | None = None) -> dict[str, Any]:
    """The output nodes of a registration result by key (``{pa,lat}`` + :data:`OUTPUT_KEYS`, ``table``;
    ``Projection`` only with a segmentation). ``outputs``: existing nodes by the same keys, updated in place
    instead of new ones; ``tick()`` is called after each view's nodes. Poses go to RAS about the CTA's grid
    centre (``geometry.frames.pose_to_patient``, as the result record's ``pose_ras``)."""
    given: dict[str, Any] = dict(outputs or {})
    out: dict[str, Any] = {}
    for key in VIEW_KEYS:
        view = result.views[key]
        _view_nodes(scene, inputs, key, view.final_pose, given, out, FINAL_RESULT, prepared_map=view.prepared.map)
        if tick is not None:
            tick()
    out["table"] = result_table_node(scene, result_rows(result, inputs.runs), "GeoPose results", node=given.get("table"))
    return out


def result_summary(table) -> str:
    """One line per view of a results table node: its mNCC and quality flag."""
    cols = {table.GetColumnName(c): c for c in range(table.GetNumberOfColumns())}
    return "\n".join(f"{table.GetCellText(r, cols['view'])}: mNCC {float(table.GetCellText(r, cols['mNCC'])):.3f}, "
                     f"{table.GetCellText(r, cols['quality'])}" for r in range(table.GetNumberOfRows()))


def register_nodes(scene, cta, dsa_pa, dsa_lat, segmentation=None, cranium_mask=None, options=None, models=None,
                   overrides: Mapping[str, Mapping] | None = None, outputs: Mapping[str, Any] | None = None,
                   progress: Callable[[str, float, str], None] | None = None, cancel: Callable[[], bool] | None = None,
                   run: Callable | None = None, tick: Callable[[], None] | None = None,
                   shown: Callable[[Any, dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Register the CTA volume node to the PA and lateral DSA run nodes: :func:`read_inputs`, then
    ``geopose.register.register_case`` (``options``, ``models``, ``progress``, ``cancel`` as it takes them;
    the CTA checked by ``validate_cta`` first), then :func:`result_nodes` into ``scene``. Returns the output
    nodes by key, ``result`` (the library's result) and ``record`` (``result.json``'s content). ``run(compute,
    progress, deliver)``: runs ``compute(report, hand_over)`` (the part that touches no node) and returns its
    result, e.g. on a worker thread, passing each ``hand_over(item)`` to ``deliver(item)`` on this thread
    (``geopose.background.run_in_background``); the networks' estimate is handed over that way, written into the
    output nodes at once (:func:`preliminary_nodes`) and then passed with them to ``shown(preliminary, nodes)``.
    Without ``run`` the registration runs here and only its final result is written. ``tick()`` is called between
    the node reads and writes."""
    from ..cta import validate_cta
    from ..register.pipeline import register_case
    from ..register.record import build_record

    inputs = read_inputs(cta, dsa_pa, dsa_lat, segmentation, cranium_mask, overrides, outputs, tick)
    name = cta.GetName()

    nodes = dict(outputs or {})

    def compute(report, hand_over=None):
        validate_cta(inputs.cta, name=f"CTA {name!r}")
        return register_case(inputs.cta, inputs.runs, models=models, options=options, cranium_mask=inputs.cranium,
                             segmentation=inputs.labels, progress=report, cancel=cancel, preliminary=hand_over)

    def deliver(preliminary) -> None:
        nodes.update(preliminary_nodes(scene, inputs, preliminary, nodes, tick))
        if shown is not None:
            shown(preliminary, nodes)

    result = run(compute, progress, deliver) if run is not None else compute(progress)
    out = result_nodes(scene, inputs, result, nodes, tick)
    out["result"] = result
    out["record"] = build_record(result, inputs.runs, inputs={"cta": {"node": name}, "dsa_pa": {"node": dsa_pa.GetName()},
                                                              "dsa_lat": {"node": dsa_lat.GetName()}})
    return out
