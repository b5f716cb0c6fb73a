"""Registration outputs as MRML nodes: pose transforms, C-arm cameras and frustums,
projected segmentations on the detector plane, and the result table.

Poses here are camera-to-world 4x4 matrices (mm): ``pose_ras`` maps the camera
frame to patient RAS, ``pose_centred`` to the centred CTA frame. Each builder takes an
optional existing ``node`` to update in place (a re-run then adds no nodes).
"""

from __future__ import annotations

import math
import weakref
from typing import Mapping, Sequence

import numpy as np
import slicer
import vtk

from ..geometry.detector import AP_REORIENT, Detector
from ..render.numpy_drr import NumpyKernel
from ..viz import to_uint8
from ..volume import Volume
from .plane import detector_ijk_to_ras, detector_index_to_camera
from .scene import matrix_from_vtk, matrix_to_vtk, output_node
from .volumes import image_data_from_array, segmentation_from_masks

__all__ = [
    "PROJECTION_THRESHOLD_VOXELS",
    "pose_transform_node",
    "transform_matrix",
    "camera_to_ras_points",
    "camera_node",
    "frustum_model_node",
    "detector_image_model_node",
    "project_labels",
    "projected_segmentation_node",
    "result_table_node",
]

#: A pixel belongs to a projected segment when its ray runs this many voxel sizes through it.
PROJECTION_THRESHOLD_VOXELS = 0.25
#: Texture sources of :func:`detector_image_model_node`, kept alive with their scene.
_TEXTURES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def pose_transform_node(
    scene: "slicer.vtkMRMLScene", pose_ras: np.ndarray, name: str, node=None
) -> "slicer.vtkMRMLLinearTransformNode":
    """A linear transform node whose to-parent matrix is the camera-to-RAS pose."""
    node = output_node(scene, "vtkMRMLLinearTransformNode", name, node)
    node.SetMatrixTransformToParent(matrix_to_vtk(pose_ras))
    return node


def transform_matrix(node: "slicer.vtkMRMLTransformNode") -> np.ndarray:
    """The to-parent 4x4 matrix of a linear transform node."""
    m = vtk.vtkMatrix4x4()
    node.GetMatrixTransformToParent(m)
    return matrix_from_vtk(m)


def camera_to_ras_points(pose_ras: np.ndarray, detector: Detector) -> dict[str, np.ndarray]:
    """RAS positions (mm) of the source, detector centre and the four detector corners
    (pixel-centre corners, rows 0/H-1 x cols 0/W-1), and the image-up direction (row 0 side)."""
    m = np.asarray(pose_ras, dtype=float) @ AP_REORIENT
    idx = detector_index_to_camera(detector)
    h, w = detector.rows - 1, detector.cols - 1
    corners_ij = np.array([[0, 0, 0, 1], [w, 0, 0, 1], [w, h, 0, 1], [0, h, 0, 1]], dtype=float)
    corners = (m @ idx @ corners_ij.T).T[:, :3]
    centre = (m @ idx @ np.array([w / 2, h / 2, 0.0, 1.0]))[:3]
    return {"source": m[:3, 3].copy(), "centre": centre, "corners": corners, "up": m[:3, :3] @ np.array([0.0, 1.0, 0.0])}


def camera_node(
    scene: "slicer.vtkMRMLScene", pose_ras: np.ndarray, detector: Detector, name: str, node=None
) -> "slicer.vtkMRMLCameraNode":
    """A camera at the X-ray source looking at the detector centre, image row 0 up,
    with the detector's vertical field of view (deg): the 3D view then sees what the C-arm sees."""
    pts = camera_to_ras_points(pose_ras, detector)
    node = output_node(scene, "vtkMRMLCameraNode", name, node)
    node.SetPosition(*pts["source"])
    node.SetFocalPoint(*pts["centre"])
    node.SetViewUp(*pts["up"])
    half_height_mm = detector.rows * detector.spacing_mm[0] / 2
    node.SetViewAngle(math.degrees(2 * math.atan(half_height_mm / detector.sdd_mm)))
    return node


def frustum_model_node(
    scene: "slicer.vtkMRMLScene", pose_ras: np.ndarray, detector: Detector, name: str, color=(1.0, 0.8, 0.0), node=None
) -> "slicer.vtkMRMLModelNode":
    """Lines from the source to the detector corners plus the detector outline (RAS mm)."""
    pts = camera_to_ras_points(pose_ras, detector)
    points = vtk.vtkPoints()
    points.InsertNextPoint(*pts["source"])
    for c in pts["corners"]:
        points.InsertNextPoint(*c)
    lines = vtk.vtkCellArray()
    for a, b in [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]:
        lines.InsertNextCell(2, (a, b))
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetLines(lines)
    node = output_node(scene, "vtkMRMLModelNode", name, node)
    node.SetAndObservePolyData(poly)
    node.CreateDefaultDisplayNodes()
    node.GetDisplayNode().SetColor(*color)
    return node


def detector_image_model_node(
    scene: "slicer.vtkMRMLScene", image: np.ndarray, detector: Detector, pose_ras: np.ndarray, name: str, node=None
) -> "slicer.vtkMRMLModelNode":
    """A flat model of the detector (RAS mm, its corners at the corner pixels' centres) textured with
    ``image (H, W)`` windowed to 8 bits (1st-99.5th percentile): the image where the C-arm saw it, in a
    3D view. (The texture is a display connection, not stored in a saved scene; a scene keeps
    the image as :func:`~geopose.mrml.plane_volume_node`.)"""
    image = np.asarray(image)
    if image.shape != detector.shape:
        raise ValueError(f"image of shape {image.shape} does not match the {detector.rows}x{detector.cols} detector")
    corners = camera_to_ras_points(pose_ras, detector)["corners"]
    plane = vtk.vtkPlaneSource()  # texture (0, 0) at row 0, column 0; s along the columns, t along the rows
    plane.SetOrigin(*corners[0])
    plane.SetPoint1(*corners[1])
    plane.SetPoint2(*corners[3])
    plane.Update()
    texture = vtk.vtkTrivialProducer()
    texture.SetOutput(image_data_from_array(to_uint8(image)[None]))
    node = output_node(scene, "vtkMRMLModelNode", name, node)
    node.SetAndObservePolyData(plane.GetOutput())
    node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    display.SetColor(1.0, 1.0, 1.0)
    display.SetAmbient(1.0)
    display.SetDiffuse(0.0)
    display.SetBackfaceCulling(0)
    display.SetTextureImageDataConnection(texture.GetOutputPort())
    _TEXTURES.setdefault(scene, {})[node.GetID()] = texture
    return node


def project_labels(
    labels: Volume, values: Sequence[int], pose_centred: np.ndarray, detector: Detector, threshold_mm: float | None = None
) -> np.ndarray:
    """Binary projections ``(len(values), H, W)`` of label-map regions onto the detector.

    ``labels`` lies on the CTA grid (its centred frame is the poses' world frame). Each
    region's indicator is ray-traced with the (numpy) DRR renderer; a pixel is set when its ray
    runs more than ``threshold_mm`` (default a quarter of the smallest voxel size) inside.
    """
    values = list(values)
    masks = np.stack([labels.array == v for v in values]) if values else np.zeros((0,) + labels.array.shape, bool)
    present = masks.any(axis=0)
    if not present.any():
        return np.zeros((len(values), detector.rows, detector.cols), dtype=bool)
    nz = np.nonzero(present)
    lo = [max(int(a.min()) - 1, 0) for a in nz]
    hi = [min(int(a.max()) + 2, n) for a, n in zip(nz, present.shape)]
    crop = masks[:, lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32)
    shift = np.eye(4)
    shift[:3, 3] = (lo[2], lo[1], lo[0])  # (i, j, k) of the crop origin
    ijk_to_world = labels.ijk_to_centred @ shift
    spacing = np.asarray(labels.spacing_mm)
    threshold = PROJECTION_THRESHOLD_VOXELS * spacing.min() if threshold_mm is None else float(threshold_mm)
    kernel = NumpyKernel(crop, ijk_to_world, float(spacing.min()))
    return kernel(pose_centred, detector, tuple(range(len(values)))) > threshold


def projected_segmentation_node(
    scene: "slicer.vtkMRMLScene",
    labels: Volume,
    segments: Mapping[int, tuple[str, tuple[float, float, float]]],
    pose_centred: np.ndarray,
    detector: Detector,
    name: str,
    node=None,
) -> "slicer.vtkMRMLSegmentationNode":
    """Segmentation on the detector plane (same grid as the DSA MAP node of this pose):
    one segment per ``{label value: (name, rgb)}``, the projection of that region."""
    proj = project_labels(labels, list(segments), pose_centred, detector)
    pose_ras = labels.centred_to_ras @ np.asarray(pose_centred, dtype=float)
    masks = {seg_name: (proj[n][None], color) for n, (seg_name, color) in enumerate(segments.values())}
    return segmentation_from_masks(scene, masks, detector_ijk_to_ras(detector, pose_ras), name, node=node)


def result_table_node(
    scene: "slicer.vtkMRMLScene", rows: Sequence[Mapping[str, object]], name: str, node=None
) -> "slicer.vtkMRMLTableNode":
    """A table with one row per mapping; numeric columns are doubles, others strings.
    Columns appear in first-seen order; a missing value is NaN (numeric) or empty."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    table = vtk.vtkTable()
    for col in columns:
        vals = [row.get(col) for row in rows]
        numeric = all(v is None or (isinstance(v, (int, float, np.number)) and not isinstance(v, bool)) for v in vals)
        arr = vtk.vtkDoubleArray() if numeric else vtk.vtkStringArray()
        arr.SetName(col)
        for v in vals:
            if numeric:
                arr.InsertNextValue(float("nan") if v is None else float(v))
            else:
                arr.InsertNextValue("" if v is None else str(v))
        table.AddColumn(arr)
    node = output_node(scene, "vtkMRMLTableNode", name, node)
    node.SetAndObserveTable(table)
    return node
