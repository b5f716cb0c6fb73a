"""DSA images on their detector planes: IJK-to-RAS of a detector image, DSA runs
as sequence nodes, and acquisition geometry kept as node attributes.

A detector image of ``H x W`` pixels is a single-slice volume with array
``[0, row, col]``, so image index ``i`` is the column and ``j`` the row. With
``A`` the index -> camera map (docs/conventions.md section 2)::

    x = ((W-1)/2 - i) * delx + x0,  y = ((H-1)/2 - j) * dely + y0,  z = SDD + k * PLANE_THICKNESS_MM

the image's IJK-to-RAS is the fixed composition
``centred_to_ras @ T @ AP_REORIENT @ A`` for a camera-to-centred pose ``T``.
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import slicer
import vtk

from ..geometry.detector import AP_REORIENT, CArmAngles, Detector
from .scene import matrix_to_vtk, output_node, sequences_logic
from .volumes import image_data_from_array

__all__ = [
    "PLANE_THICKNESS_MM",
    "ATTRIBUTE_PREFIX",
    "detector_index_to_camera",
    "detector_ijk_to_ras",
    "plane_axes",
    "plane_volume_node",
    "dsa_sequence_node",
    "frames_from_sequence",
    "frames_from_node",
    "proxy_name",
    "proxy_sequence",
    "sequence_proxy_ids",
    "set_geometry_attributes",
    "geometry_from_attributes",
]

#: Nominal slice thickness of a detector image (mm), along the beam direction.
PLANE_THICKNESS_MM = 1.0
#: Prefix of the node attributes that keep the acquisition geometry.
ATTRIBUTE_PREFIX = "GeoPose."


def detector_index_to_camera(detector: Detector) -> np.ndarray:
    """4x4 from detector-image index ``(i = column, j = row, k)`` to the camera frame (mm)."""
    dy, dx = detector.spacing_mm
    x0, y0 = detector.principal_offset_mm
    a = np.diag([-dx, -dy, PLANE_THICKNESS_MM, 1.0])
    a[:3, 3] = ((detector.cols - 1) / 2 * dx + x0, (detector.rows - 1) / 2 * dy + y0, detector.sdd_mm)
    return a


def detector_ijk_to_ras(detector: Detector, pose_ras: np.ndarray) -> np.ndarray:
    """IJK-to-RAS 4x4 of a detector image for a camera-to-RAS pose ``pose_ras`` (mm)."""
    pose_ras = np.asarray(pose_ras, dtype=float)
    if pose_ras.shape != (4, 4):
        raise ValueError(f"a pose is a 4x4 camera-to-RAS matrix, got shape {pose_ras.shape}")
    return pose_ras @ AP_REORIENT @ detector_index_to_camera(detector)


def plane_axes(node) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(normal, column direction, centre)`` in RAS of a detector-plane volume node (a single-slice volume,
    e.g. :func:`plane_volume_node`'s): unit vectors along its k and i axes and its centre pixel's position (mm),
    what a slice view needs to show the plane (``SetSliceToRASByNTP``)."""
    from .volumes import volume_from_node

    vol = volume_from_node(node)
    m = vol.ijk_to_ras
    i, j, _k = vol.shape_ijk
    centre = m @ [(i - 1) / 2, (j - 1) / 2, 0, 1]
    return m[:3, 2] / np.linalg.norm(m[:3, 2]), m[:3, 0] / np.linalg.norm(m[:3, 0]), centre[:3]


def _check_image(image: np.ndarray, detector: Detector) -> np.ndarray:
    image = np.asarray(image)
    if image.shape[-2:] != detector.shape:
        raise ValueError(f"image of shape {image.shape[-2:]} does not match the {detector.rows}x{detector.cols} detector")
    return image


def plane_volume_node(
    scene: "slicer.vtkMRMLScene", image: np.ndarray, detector: Detector, pose_ras: np.ndarray, name: str, node=None
) -> "slicer.vtkMRMLScalarVolumeNode":
    """A single-slice scalar volume holding ``image (H, W)`` on its detector plane (``node``: updated in place)."""
    image = _check_image(image, detector)
    if image.ndim != 2:
        raise ValueError(f"a detector image is (H, W), got shape {image.shape}")
    node = output_node(scene, "vtkMRMLScalarVolumeNode", name, node)
    node.SetIJKToRASMatrix(matrix_to_vtk(detector_ijk_to_ras(detector, pose_ras)))
    node.SetAndObserveImageData(image_data_from_array(image[None]))
    node.CreateDefaultDisplayNodes()
    return node


def dsa_sequence_node(
    scene: "slicer.vtkMRMLScene",
    frames: np.ndarray,
    detector: Detector,
    pose_ras: np.ndarray,
    name: str,
    frame_time_s: float | None = None,
    angles: CArmAngles | None = None,
    node=None,
) -> tuple["slicer.vtkMRMLSequenceNode", "slicer.vtkMRMLSequenceBrowserNode"]:
    """A DSA run ``frames (T, H, W)`` as a sequence of single-slice volumes on the detector
    plane of ``pose_ras``, indexed by time (s, or frame number without a frame time), with a browser.
    An existing sequence ``node`` gets these frames instead of its own and keeps its browser."""
    frames = _check_image(frames, detector)
    if frames.ndim != 3 or frames.shape[0] < 1:
        raise ValueError(f"a DSA run is (T, H, W) with T >= 1, got shape {frames.shape}")
    ijk_to_ras = matrix_to_vtk(detector_ijk_to_ras(detector, pose_ras))
    seq = output_node(scene, "vtkMRMLSequenceNode", name, node)
    seq.RemoveAllDataNodes()
    seq.SetIndexName("time" if frame_time_s else "frame")
    seq.SetIndexUnit("s" if frame_time_s else "")
    seq.SetIndexType(seq.NumericIndex)
    for t, frame in enumerate(frames):
        node = slicer.vtkMRMLScalarVolumeNode()
        node.SetName(f"{name} frame {t}")
        node.SetIJKToRASMatrix(ijk_to_ras)
        node.SetAndObserveImageData(image_data_from_array(frame[None]))
        seq.SetDataNodeAtValue(node, f"{t * frame_time_s:.6g}" if frame_time_s else str(t))
    set_geometry_attributes(seq, detector, angles, frame_time_s)
    logic = sequences_logic(scene)
    browser = logic.GetFirstBrowserNodeForSequenceNode(seq)
    if browser is None:
        browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", f"{seq.GetName()} browser")
        browser.SetAndObserveMasterSequenceNodeID(seq.GetID())
    browser.SetOverwriteProxyName(seq, False)  # the browser would name the proxy like the sequence
    logic.UpdateProxyNodesFromSequences(browser)
    proxy = browser.GetProxyNode(seq)
    if proxy is not None:
        proxy.SetName(proxy_name(seq.GetName()))
        proxy.CreateDefaultDisplayNodes()
    return seq, browser


def proxy_name(sequence_name: str) -> str:
    """Name of the volume that shows a DSA sequence's current frame (its browser's proxy): not the sequence's own."""
    return f"{sequence_name} (shown frame)"


def proxy_sequence(node) -> "slicer.vtkMRMLSequenceNode | None":
    """The sequence whose current item ``node`` shows (``node`` is a sequence browser's proxy), else None."""
    scene = node.GetScene() if node is not None else None
    if scene is None:
        return None
    for n in range(scene.GetNumberOfNodesByClass("vtkMRMLSequenceBrowserNode")):
        browser = scene.GetNthNodeByClass(n, "vtkMRMLSequenceBrowserNode")
        if browser.IsProxyNodeID(node.GetID()):
            return browser.GetSequenceNode(node)
    return None


def sequence_proxy_ids(scene: "slicer.vtkMRMLScene") -> list[str]:
    """IDs of every sequence browser's proxy nodes in ``scene`` (what a node selector hides, as they are not inputs)."""
    ids = []
    for n in range(scene.GetNumberOfNodesByClass("vtkMRMLSequenceBrowserNode")):
        proxies = vtk.vtkCollection()
        scene.GetNthNodeByClass(n, "vtkMRMLSequenceBrowserNode").GetAllProxyNodes(proxies)
        ids += [proxies.GetItemAsObject(i).GetID() for i in range(proxies.GetNumberOfItems())]
    return ids


def frames_from_sequence(seq: "slicer.vtkMRMLSequenceNode") -> np.ndarray:
    """Stack a sequence of single-slice scalar volumes into ``(T, H, W)``."""
    from .volumes import volume_from_node

    if seq is None or not seq.IsA("vtkMRMLSequenceNode") or seq.GetNumberOfDataNodes() == 0:
        raise ValueError("expected a non-empty sequence node of DSA frames")
    frames = []
    for n in range(seq.GetNumberOfDataNodes()):
        node = seq.GetNthDataNode(n)
        if not node.IsA("vtkMRMLScalarVolumeNode"):
            raise ValueError(f"sequence {seq.GetName()!r} holds {node.GetClassName()} items, not image volumes")
        arr = volume_from_node(node).array
        if arr.shape[0] != 1:
            raise ValueError(f"frame {n} of {seq.GetName()!r} has {arr.shape[0]} slices; a DSA frame has one")
        frames.append(arr[0])
    if len({f.shape for f in frames}) != 1:
        raise ValueError(f"the frames of {seq.GetName()!r} differ in size")
    return np.stack(frames)


def frames_from_node(node) -> np.ndarray:
    """DSA frames ``(T, H, W)`` from a sequence node or a multi-frame volume (frames along k)."""
    from .volumes import volume_from_node

    if node is not None and node.IsA("vtkMRMLSequenceNode"):
        return frames_from_sequence(node)
    if node is not None and node.IsA("vtkMRMLScalarVolumeNode"):
        return volume_from_node(node).array
    raise ValueError("a DSA input is a sequence node or a scalar volume node (frames along k)")


def set_geometry_attributes(
    node, detector: Detector, angles: CArmAngles | None = None, frame_time_s: float | None = None
) -> None:
    """Keep detector intrinsics, C-arm angles (deg, mm) and frame time (s) as ``GeoPose.*`` attributes."""
    values: dict[str, object] = {f"Detector.{k}": v for k, v in asdict(detector).items()}
    if angles is not None:
        values.update({f"CArm.{k}": v for k, v in asdict(angles).items()})
    if frame_time_s:
        values["FrameTime_s"] = frame_time_s
    for key, value in values.items():
        text = " ".join(f"{x:.10g}" for x in value) if isinstance(value, (tuple, list)) else f"{value:.10g}"
        node.SetAttribute(ATTRIBUTE_PREFIX + key, text)


def _attr(node, key: str, n: int | None = None):
    text = node.GetAttribute(ATTRIBUTE_PREFIX + key)
    if text is None:
        return None
    vals = [float(v) for v in text.split()]
    return tuple(vals) if n else vals[0]


def geometry_from_attributes(node) -> tuple[Detector | None, CArmAngles | None, float | None]:
    """Inverse of :func:`set_geometry_attributes`; ``None`` for what the node does not carry."""
    detector = None
    if _attr(node, "Detector.rows") is not None:
        detector = Detector(
            rows=int(_attr(node, "Detector.rows")),
            cols=int(_attr(node, "Detector.cols")),
            spacing_mm=_attr(node, "Detector.spacing_mm", 2),
            sdd_mm=_attr(node, "Detector.sdd_mm"),
            principal_offset_mm=_attr(node, "Detector.principal_offset_mm", 2),
        )
    angles = None
    if _attr(node, "CArm.primary_deg") is not None:
        angles = CArmAngles(
            primary_deg=_attr(node, "CArm.primary_deg"),
            secondary_deg=_attr(node, "CArm.secondary_deg"),
            sid_mm=_attr(node, "CArm.sid_mm"),
            sod_mm=_attr(node, "CArm.sod_mm"),
            roll_deg=_attr(node, "CArm.roll_deg"),
            offset_mm=_attr(node, "CArm.offset_mm", 2),
        )
    return detector, angles, _attr(node, "FrameTime_s")
