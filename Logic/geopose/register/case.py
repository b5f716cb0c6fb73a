"""What every registration path shares before the stages run (no PyTorch): the view
keys, the combined CTA label map the renderers split into channels, and the
preprocessed PA / lateral runs checked against their roles."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .. import contract as C
from ..cta import cranium_mask_from_cta, vessel_mask_from_cta
from ..dsa import LAT_ROLE, PA_ROLE, DSARun, PreparedDSA, preprocess_dsa
from ..volume import Volume
from .progress import Monitor

__all__ = [
    "VIEW_KEYS", "TTO_PX_CUDA", "TTO_PX_CPU", "CRANIUM_BIT", "VESSEL_BIT", "LABEL_GROUPS", "CRANIUM_CHANNEL",
    "VESSEL_CHANNEL", "case_labels", "check_view_keys", "prepare_views", "silhouette_dice",
]

VIEW_KEYS = ("pa", "lat")
#: Label values of the combined CTA label map handed to the renderer.
CRANIUM_BIT = 1
VESSEL_BIT = 2
LABEL_GROUPS = {"cranium": [CRANIUM_BIT, CRANIUM_BIT | VESSEL_BIT], "vessels": [VESSEL_BIT, CRANIUM_BIT | VESSEL_BIT]}
#: Default TTO image size (pixels along the detector's longer side): the GPU affords
#: the model resolution; on a CPU half of it keeps a registration under a minute.
TTO_PX_CUDA = 256
TTO_PX_CPU = 128
#: Renderer channels: 0 total density, then the label groups in order.
CRANIUM_CHANNEL = 1
VESSEL_CHANNEL = 2


def case_labels(cta: Volume, cranium_mask: Volume | None, segmentation: Volume | None) -> tuple[Volume, dict]:
    """Combined label map (cranium bit 1, vessel bit 2) on the CTA grid, and where each part came from.

    Missing parts are computed from the CTA (``geopose.cta.masks``); the vessel
    part is then a contrast-threshold approximation and the record says so.
    """
    source = {}
    for name, vol in (("cranium mask", cranium_mask), ("segmentation", segmentation)):
        if vol is not None and vol.array.shape != cta.array.shape:
            raise ValueError(
                f"the {name} grid {vol.shape_ijk} differs from the CTA grid {cta.shape_ijk}: resample it onto the CTA first"
            )
    if cranium_mask is None:
        cranium_mask = cranium_mask_from_cta(cta)
        source["cranium"] = "computed from the CTA (bone threshold, largest component, filled)"
    else:
        source["cranium"] = "given"
    if segmentation is None:
        vessels = vessel_mask_from_cta(cta, cranium_mask).array > 0
        source["vessels"] = "contrast-threshold vessel mask inside the cranium (no segmentation given)"
    else:
        vessels = segmentation.array > 0
        source["vessels"] = "given segmentation"
    combined = (cranium_mask.array > 0).astype(np.uint8) * CRANIUM_BIT + vessels.astype(np.uint8) * VESSEL_BIT
    return cta.like(combined, role="geopose case labels"), source


def check_view_keys(dsa: Mapping[str, DSARun]) -> None:
    """A case is one PA and one lateral run keyed ``{"pa": ..., "lat": ...}``."""
    if set(dsa) != set(VIEW_KEYS):
        raise ValueError(f"need one PA and one lateral DSA run as {{'pa': ..., 'lat': ...}}, got {sorted(dsa)}")


def silhouette_dice(silhouette: np.ndarray, reference: np.ndarray) -> float:
    """Hard Dice of the projected CTA cranium (``silhouette > 0``) and the DSA cranium mask
    (``reference > 0``) on the same detector; 1 when both are empty."""
    sil, ref = np.asarray(silhouette) > 0, np.asarray(reference) > 0
    denom = int(sil.sum()) + int(ref.sum())
    return 1.0 if denom == 0 else 2.0 * int((sil & ref).sum()) / denom


def prepare_views(
    dsa: Mapping[str, DSARun], *, tto_px: int, dsa_masks: Mapping[str, np.ndarray] | None = None,
    monitor: Monitor | None = None, model_clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES,
) -> dict[str, PreparedDSA]:
    """Preprocess ``{"pa": run, "lat": run}`` (CONVENTIONS 5), TTO targets at ``tto_px``,
    the networks' images clipped to ``model_clip_percentiles``; the 'pa' run must look PA
    and the 'lat' run lateral by their primary angles."""
    monitor = monitor or Monitor()
    check_view_keys(dsa)
    prepared: dict[str, PreparedDSA] = {}
    for i, key in enumerate(VIEW_KEYS):
        monitor.step("prepare", (i + 1) / 3, f"DSA {key.upper()}")
        kwargs = {"mask": dsa_masks[key]} if dsa_masks and key in dsa_masks else {}
        prepared[key] = preprocess_dsa(dsa[key], tto_px=tto_px, model_clip_percentiles=model_clip_percentiles, **kwargs)
    if prepared["pa"].view_role != PA_ROLE or prepared["lat"].view_role != LAT_ROLE:
        raise ValueError(
            f"the 'pa' run looks {prepared['pa'].view_role} and the 'lat' run {prepared['lat'].view_role} by their "
            "primary angles: swap them, or override the angle (primary_deg) if the tags are wrong"
        )
    return prepared
