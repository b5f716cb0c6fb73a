"""CT(A) input: loading and validation in HU, saving, cranium and vessel masks."""

from .io import CTA_EXTENSIONS, file_sha256, load_cta, save_volume, sitk_from_volume, validate_cta, volume_from_sitk
from .masks import cranium_mask_from_cta, vessel_mask_from_cta

__all__ = [
    "CTA_EXTENSIONS",
    "cranium_mask_from_cta",
    "file_sha256",
    "load_cta",
    "save_volume",
    "sitk_from_volume",
    "validate_cta",
    "vessel_mask_from_cta",
    "volume_from_sitk",
]
