"""MRML adapters: ``geopose`` data <-> 3D Slicer scene nodes.

Pure functions over a ``vtkMRMLScene``; they run inside 3D Slicer and in plain
Python with the ``slicer-core`` wheel (no Qt). The rest of the ``geopose``
library never imports this package.
"""

from __future__ import annotations

try:
    import slicer  # noqa: F401
    from slicer import vtkMRMLScene  # noqa: F401
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError(
        "geopose.mrml needs 3D Slicer's MRML classes: run it inside 3D Slicer "
        "or install the 'slicer-core' wheel (pip install slicer-core)"
    ) from exc

from .scene import load_mrb, matrix_from_vtk, matrix_to_vtk, new_scene, output_node, prepare_scene, save_mrb, sequences_logic
from .volumes import (
    labelmap_from_segmentation,
    read_volume_node,
    segment_colors,
    segmentation_from_labelmap,
    segmentation_from_masks,
    volume_from_node,
    volume_to_node,
)
from .plane import (
    detector_ijk_to_ras,
    dsa_sequence_node,
    frames_from_node,
    frames_from_sequence,
    geometry_from_attributes,
    plane_axes,
    plane_volume_node,
    proxy_name,
    proxy_sequence,
    sequence_proxy_ids,
    set_geometry_attributes,
)
from .outputs import (
    camera_node,
    camera_to_ras_points,
    detector_image_model_node,
    frustum_model_node,
    pose_transform_node,
    projected_segmentation_node,
    project_labels,
    result_table_node,
    transform_matrix,
)
from .registration import (
    OUTPUT_KEYS,
    FINAL_RESULT,
    PRELIMINARY_RESULT,
    RESULT_ATTRIBUTE,
    VIEW_KEYS,
    VIEW_TITLES,
    RegistrationInputs,
    dsa_image_ids,
    first_cta_candidate,
    geometry_overrides,
    is_dsa_image,
    read_dsa_node,
    preliminary_nodes,
    read_inputs,
    register_nodes,
    result_nodes,
    result_rows,
    result_summary,
    run_from_node,
    segmentation_labels,
)

__all__ = [
    "camera_node", "camera_to_ras_points", "detector_image_model_node", "detector_ijk_to_ras", "dsa_sequence_node", "frames_from_node",
    "frames_from_sequence", "frustum_model_node",
    "geometry_from_attributes", "labelmap_from_segmentation", "load_mrb", "matrix_from_vtk", "matrix_to_vtk",
    "new_scene", "output_node", "plane_volume_node", "pose_transform_node", "prepare_scene", "project_labels",
    "proxy_name", "proxy_sequence", "sequence_proxy_ids",
    "projected_segmentation_node", "read_volume_node", "result_table_node", "save_mrb",
    "segment_colors", "segmentation_from_labelmap", "segmentation_from_masks", "set_geometry_attributes", "volume_from_node", "volume_to_node",
    "sequences_logic", "transform_matrix", "plane_axes",
    "OUTPUT_KEYS", "VIEW_KEYS", "VIEW_TITLES", "RegistrationInputs", "dsa_image_ids", "first_cta_candidate",
    "geometry_overrides", "is_dsa_image", "preliminary_nodes", "read_dsa_node", "read_inputs", "register_nodes",
    "result_nodes", "result_rows", "FINAL_RESULT", "PRELIMINARY_RESULT", "RESULT_ATTRIBUTE",
    "result_summary", "run_from_node", "segmentation_labels",
]
