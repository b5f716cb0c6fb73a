"""C-arm and rigid geometry: detectors, DICOM angles, numpy poses (inference), torch
transforms (training, test-time optimisation), the centred and patient frames."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "detector": (
            "AP_REORIENT", "CArmAngles", "Detector", "carm_angles_from_params", "carm_pose_params",
            "is_lateral_primary_angle", "view_from_primary_angle",
        ),
        "poses": (
            "axis_angle_to_matrix", "carm_angles_from_pose", "euler_zyx_to_matrix", "invert", "isopose", "matrix_to_axis_angle",
            "matrix_to_euler_zyx", "params_from_pose", "pose_from_carm_angles", "pose_from_params", "project_points",
            "rotation_angle_rad", "source_and_detector_points",
        ),
        "carm": ("project_points_tensor", "ray_points_tensor"),
        "frames": ("centred_to_patient", "pose_to_patient", "pose_from_patient", "RAS_TO_LPS"),
        "rigid": ("RigidTransform",),
    },
)
