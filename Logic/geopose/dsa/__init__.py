"""DSA input: the run contract, readers, writers, geometry overrides and preprocessing."""

from .cli_args import geometry_override_args, geometry_overrides_from_args
from .preprocess import (
    PreparedDSA,
    bilateral,
    clip_intensities,
    dsa_cranium_mask,
    intensity_unit,
    minmax,
    preprocess_dsa,
    resample_to_detector,
    resample_to_model_sdd,
    temporal_map,
)
from .readers import read_dsa, sidecar_path
from .run import GEOMETRY_KEYS, LAT_ROLE, PA_ROLE, DSAInputError, DSARun
from .writers import quantize_frames, write_dsa_dicom, write_dsa_nifti

__all__ = [
    "DSAInputError",
    "DSARun",
    "GEOMETRY_KEYS",
    "LAT_ROLE",
    "PA_ROLE",
    "PreparedDSA",
    "bilateral",
    "clip_intensities",
    "dsa_cranium_mask",
    "geometry_override_args",
    "geometry_overrides_from_args",
    "intensity_unit",
    "minmax",
    "preprocess_dsa",
    "quantize_frames",
    "read_dsa",
    "resample_to_detector",
    "resample_to_model_sdd",
    "sidecar_path",
    "temporal_map",
    "write_dsa_dicom",
    "write_dsa_nifti",
]
