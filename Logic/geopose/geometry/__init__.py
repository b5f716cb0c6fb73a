"""C-arm and rigid geometry: poses, detectors, isoposes, DICOM angles, frames."""

from .carm import (
    AP_REORIENT,
    CArmAngles,
    Detector,
    backproject_pixels,
    carm_angles_from_pose,
    is_lateral_primary_angle,
    isopose,
    pose_from_carm_angles,
    project_points,
    source_and_detector_points,
    view_from_primary_angle,
)
from .frames import centred_to_patient, pose_to_patient, pose_from_patient, RAS_TO_LPS
from .rigid import (
    RigidTransform,
    axis_angle_to_matrix,
    euler_zyx_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler_zyx,
    params_from_pose,
    pose_from_params,
    rotation_angle_rad,
)

__all__ = [
    "AP_REORIENT", "CArmAngles", "Detector", "RAS_TO_LPS", "RigidTransform",
    "axis_angle_to_matrix", "backproject_pixels", "carm_angles_from_pose", "centred_to_patient",
    "euler_zyx_to_matrix", "is_lateral_primary_angle", "isopose", "matrix_to_axis_angle",
    "matrix_to_euler_zyx", "params_from_pose", "pose_from_carm_angles", "pose_from_params",
    "pose_from_patient", "pose_to_patient", "project_points", "rotation_angle_rad",
    "source_and_detector_points", "view_from_primary_angle",
]
