"""C-arm and rigid geometry: poses, detectors, isoposes, DICOM angles, frames."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "detector": (
            "AP_REORIENT", "CArmAngles", "Detector", "carm_pose_params", "is_lateral_primary_angle",
            "view_from_primary_angle",
        ),
        "carm": (
            "backproject_pixels", "carm_angles_from_pose", "isopose", "pose_from_carm_angles", "project_points",
            "source_and_detector_points",
        ),
        "frames": ("centred_to_patient", "pose_to_patient", "pose_from_patient", "RAS_TO_LPS"),
        "rigid": (
            "RigidTransform", "axis_angle_to_matrix", "euler_zyx_to_matrix", "matrix_to_axis_angle",
            "matrix_to_euler_zyx", "params_from_pose", "pose_from_params", "rotation_angle_rad",
        ),
    },
)
