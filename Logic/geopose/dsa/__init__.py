"""DSA input: the run contract, readers (native runs subtracted), writers, geometry overrides and preprocessing."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "cli_args": ("geometry_override_args", "geometry_overrides_from_args"),
        "preprocess": (
            "PreparedDSA", "bilateral", "bolus_weighted_mean", "clip_intensities", "dsa_cranium_mask", "early_frames_mean",
            "intensity_unit", "minmax", "preprocess_dsa", "resample_to_detector", "resample_to_model_sdd", "temporal_map",
        ),
        "readers": ("read_dsa", "run_from_geometry", "sidecar_path"),
        "run": ("GEOMETRY_KEYS", "LAT_ROLE", "PA_ROLE", "DSARun"),
        "subtraction": ("MaskSubtraction", "read_mask_subtraction", "subtract_mask"),
        "writers": ("quantize_frames", "write_dsa_dicom", "write_dsa_nifti"),
    },
)
