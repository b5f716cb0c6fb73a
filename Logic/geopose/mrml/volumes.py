"""Scalar volume, label-map and segmentation nodes <-> :class:`geopose.volume.Volume`.

A volume node's image data is stored i-fastest, i.e. numpy order ``[k, j, i]``,
the same order as ``Volume.array``; ``IJKToRAS`` is ``Volume.ijk_to_ras``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import slicer
import vtk
from vtk.util import numpy_support

from ..volume import Volume
from .scene import matrix_from_vtk, matrix_to_vtk, output_node

__all__ = [
    "volume_from_node",
    "volume_to_node",
    "image_data_from_array",
    "labelmap_from_segmentation",
    "segmentation_from_labelmap",
    "segmentation_from_masks",
    "segment_colors",
    "read_volume_node",
]

#: Largest deviation from orthogonality (cosine) accepted for an IJK-to-RAS matrix.
_ORTHOGONALITY_TOL = 1e-4


def _array_from_image(image: vtk.vtkImageData) -> np.ndarray:
    if image is None or image.GetPointData().GetScalars() is None:
        raise ValueError("the node has no image data: load or create an image first")
    if image.GetNumberOfScalarComponents() != 1:
        raise ValueError(f"expected a single-component (scalar) image, got {image.GetNumberOfScalarComponents()} components")
    i, j, k = image.GetDimensions()
    return numpy_support.vtk_to_numpy(image.GetPointData().GetScalars()).reshape(k, j, i).copy()


def image_data_from_array(array: np.ndarray, image: vtk.vtkImageData | None = None) -> vtk.vtkImageData:
    """A new (or the given) ``vtkImageData`` holding a copy of ``array[k, j, i]`` (origin 0, spacing 1)."""
    array = np.asarray(array)
    if array.ndim != 3:
        raise ValueError(f"image data needs a 3D [k, j, i] array, got shape {array.shape}")
    if array.dtype == bool:
        array = array.astype(np.uint8)
    image = image if image is not None else vtk.vtkImageData()
    k, j, i = array.shape
    image.SetDimensions(i, j, k)
    scalars = numpy_support.numpy_to_vtk(np.ascontiguousarray(array).ravel(), deep=1)
    scalars.SetName("ImageScalars")
    image.GetPointData().SetScalars(scalars)
    return image


def volume_from_node(node: "slicer.vtkMRMLScalarVolumeNode") -> Volume:
    """Copy a scalar or label-map volume node into a :class:`Volume` (world transforms are not applied)."""
    if node is None or not node.IsA("vtkMRMLScalarVolumeNode"):
        raise ValueError("expected a scalar or label-map volume node; select a volume in the scene")
    if node.GetParentTransformNode() is not None:
        raise ValueError(
            f"volume {node.GetName()!r} is under a transform: harden the transform (Transforms module) before registering"
        )
    m = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(m)
    return Volume(_array_from_image(node.GetImageData()), matrix_from_vtk(m), {"name": node.GetName()})


def _check_orthogonal(ijk_to_ras: np.ndarray) -> None:
    axes = ijk_to_ras[:3, :3] / np.linalg.norm(ijk_to_ras[:3, :3], axis=0)
    off = np.abs(axes.T @ axes - np.eye(3)).max()
    if off > _ORTHOGONALITY_TOL:
        raise ValueError("the IJK-to-RAS matrix is sheared; MRML volumes need orthogonal axes: resample the image first")


def volume_to_node(
    scene: "slicer.vtkMRMLScene", volume: Volume, name: str, labelmap: bool = False
) -> "slicer.vtkMRMLScalarVolumeNode":
    """Add a scalar (or label-map) volume node holding a copy of ``volume``."""
    _check_orthogonal(volume.ijk_to_ras)
    cls = "vtkMRMLLabelMapVolumeNode" if labelmap else "vtkMRMLScalarVolumeNode"
    node = scene.AddNewNodeByClass(cls, name)
    node.SetIJKToRASMatrix(matrix_to_vtk(volume.ijk_to_ras))
    node.SetAndObserveImageData(image_data_from_array(volume.array))
    node.CreateDefaultDisplayNodes()
    return node


def labelmap_from_segmentation(
    segmentation: "slicer.vtkMRMLSegmentationNode",
    reference: "slicer.vtkMRMLScalarVolumeNode",
    segment_ids: Sequence[str] | None = None,
) -> tuple[Volume, dict[str, int]]:
    """Label map on ``reference``'s grid; returns it and ``{segment name: label value}`` (1, 2, ...).

    Overlapping segments take the value of the later one. The scene is left as it was.
    """
    if segmentation is None or not segmentation.IsA("vtkMRMLSegmentationNode"):
        raise ValueError("expected a segmentation node; select the vessel segmentation")
    seg = segmentation.GetSegmentation()
    ids = list(segment_ids) if segment_ids is not None else list(seg.GetSegmentIDs())
    if not ids:
        raise ValueError(f"segmentation {segmentation.GetName()!r} has no segments: add at least one segment")
    missing = [s for s in ids if seg.GetSegment(s) is None]
    if missing:
        raise ValueError(f"segments {missing} are not in {segmentation.GetName()!r}; available: {list(seg.GetSegmentIDs())}")
    scene = segmentation.GetScene()
    ids_vtk = vtk.vtkStringArray()
    for s in ids:
        ids_vtk.InsertNextValue(s)
    existing = {scene.GetNthNode(n).GetID() for n in range(scene.GetNumberOfNodes())}
    tmp = scene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "__geopose_tmp_labels__")
    try:
        ok = slicer.vtkSlicerSegmentationsModuleLogic.ExportSegmentsToLabelmapNode(segmentation, ids_vtk, tmp, reference)
        if not ok:
            raise ValueError(f"could not export {segmentation.GetName()!r} to a label map on {reference.GetName()!r}")
        labels = volume_from_node(tmp)
    finally:  # remove the temporary label map and what the export added (display, colour table)
        added = [scene.GetNthNode(n) for n in range(scene.GetNumberOfNodes())]
        for node in added:
            if node.GetID() not in existing:
                scene.RemoveNode(node)
    names = {seg.GetSegment(s).GetName(): n + 1 for n, s in enumerate(ids)}
    return Volume(labels.array, labels.ijk_to_ras, {"segments": names}), names


def segmentation_from_masks(
    scene: "slicer.vtkMRMLScene",
    masks: Mapping[str, tuple[np.ndarray, tuple[float, float, float]]],
    ijk_to_ras: np.ndarray,
    name: str,
    node=None,
) -> "slicer.vtkMRMLSegmentationNode":
    """A segmentation node with one binary-labelmap segment per ``{name: (mask [k, j, i], rgb 0..1)}``
    on the grid ``ijk_to_ras`` (segments may overlap); an existing ``node`` gets these segments instead of its own."""
    ijk_to_ras = np.asarray(ijk_to_ras, dtype=float)
    _check_orthogonal(ijk_to_ras)
    node = output_node(scene, "vtkMRMLSegmentationNode", name, node)
    node.CreateDefaultDisplayNodes()
    seg = node.GetSegmentation()
    seg.RemoveAllSegments()
    rep = slicer.vtkSegmentationConverter.GetBinaryLabelmapRepresentationName()
    seg.SetSourceRepresentationName(rep)
    for seg_name, (mask, color) in masks.items():
        image = slicer.vtkOrientedImageData()
        image_data_from_array(np.asarray(mask).astype(np.uint8), image)
        image.SetImageToWorldMatrix(matrix_to_vtk(ijk_to_ras))
        segment = slicer.vtkSegment()
        segment.SetName(seg_name)
        segment.SetColor(*[float(c) for c in color])
        segment.AddRepresentation(rep, image)
        seg.AddSegment(segment, seg_name)
    return node


def segmentation_from_labelmap(
    scene: "slicer.vtkMRMLScene",
    labels: Volume,
    segments: Mapping[int, tuple[str, tuple[float, float, float]]],
    name: str,
) -> "slicer.vtkMRMLSegmentationNode":
    """A segmentation node with one segment per ``{label value: (name, rgb 0..1)}``."""
    masks = {seg_name: (labels.array == value, color) for value, (seg_name, color) in segments.items()}
    return segmentation_from_masks(scene, masks, labels.ijk_to_ras, name)


def segment_colors(segmentation: "slicer.vtkMRMLSegmentationNode") -> dict[str, tuple[float, float, float]]:
    """``{segment name: rgb 0..1}`` of a segmentation node."""
    seg = segmentation.GetSegmentation()
    return {seg.GetSegment(s).GetName(): tuple(seg.GetSegment(s).GetColor()) for s in seg.GetSegmentIDs()}


def read_volume_node(
    scene: "slicer.vtkMRMLScene", path: str | Path, name: str | None = None, labelmap: bool = False
) -> "slicer.vtkMRMLScalarVolumeNode":
    """Read an image file (NIfTI, NRRD, MHA, ...) into a new volume node through a storage node."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    cls = "vtkMRMLLabelMapVolumeNode" if labelmap else "vtkMRMLScalarVolumeNode"
    node = scene.AddNewNodeByClass(cls, name or path.name.split(".")[0])
    storage = scene.AddNewNodeByClass("vtkMRMLVolumeArchetypeStorageNode")
    storage.SetFileName(str(path))
    storage.SetSingleFile(True)
    node.SetAndObserveStorageNodeID(storage.GetID())
    if not storage.ReadData(node):
        scene.RemoveNode(node)
        scene.RemoveNode(storage)
        raise ValueError(f"could not read {path} as an image volume: check the file format (NIfTI, NRRD, MHA)")
    node.CreateDefaultDisplayNodes()
    return node
