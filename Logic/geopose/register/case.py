"""A case ready for the registration stages (no PyTorch): the CTA as the renderers see
it (a :class:`~geopose.render.volume.RenderVolume` with its cranium and vessel masks)
and each view's preprocessed DSA, checked against its role."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .. import contract as C
from ..cta import cranium_mask_from_cta, vessel_mask_from_cta
from ..dsa import LAT_ROLE, PA_ROLE, DSARun, PreparedDSA, preprocess_dsa
from ..errors import InputError
from ..options import TTO_PX_CPU
from ..render.density import DensityScale
from ..render.volume import RenderVolume, coarse_mask, render_factors
from ..volume import Volume
from .progress import Monitor

__all__ = ["VIEW_KEYS", "PreparedCase", "prepare_case", "check_view_keys", "silhouette_dice"]

VIEW_KEYS = ("pa", "lat")


@dataclass(frozen=True)
class PreparedCase:
    """The CTA's :class:`RenderVolume`, where each mask came from (``labels_source``; a computed vessel mask made with
    the artery classifier adds ``artery_classifier_sha256``), and each view's preprocessed DSA (``views``, keyed ``pa`` /
    ``lat``)."""

    cta: Volume
    volume: RenderVolume
    labels_source: dict[str, str]
    views: dict[str, PreparedDSA]

    @property
    def arteries_classified(self) -> bool:
        """Whether the vessel mask was computed from the CTA and kept what the artery classifier calls artery
        (``cta/masks.py``; a CTA no coarser than ``ARTERY_CLASSIFIER_MAX_MM``), which makes it mostly artery."""
        return self.vessel_evidence and "artery_classifier_sha256" in self.labels_source

    @property
    def vessel_evidence(self) -> bool:
        """Whether the CTA's vessel mask (given, or computed on first use) holds any vessel."""
        vessels = self.volume.mask("vessels")
        return vessels is not None and bool(vessels.any())

    def model_target(self, key: str) -> np.ndarray:
        """View ``key``'s model-geometry MAP ``(1, 1, 256, 256)`` float32 (the networks' image)."""
        return self.views[key].model_image[None, None].astype(np.float32)

    def model_targets(self) -> dict[str, np.ndarray]:
        """Every view's :meth:`model_target`."""
        return {key: self.model_target(key) for key in VIEW_KEYS}

    def view_labels(self) -> dict[str, int]:
        """Every view's label by its acquisition angle (``contract.VIEW_*``)."""
        return {key: self.views[key].view_label for key in VIEW_KEYS}


def check_view_keys(dsa: Mapping[str, object]) -> None:
    """A case is one PA and one lateral run keyed ``{"pa": ..., "lat": ...}``."""
    if set(dsa) != set(VIEW_KEYS):
        raise InputError(f"need one PA and one lateral DSA run as {{'pa': ..., 'lat': ...}}, got {sorted(dsa)}")


def silhouette_dice(silhouette: np.ndarray, reference: np.ndarray) -> float:
    """Hard Dice of the projected CTA cranium (``silhouette > 0``) and the DSA cranium mask
    (``reference > 0``) on the same detector; 1 when both are empty."""
    sil, ref = np.asarray(silhouette) > 0, np.asarray(reference) > 0
    denom = int(sil.sum()) + int(ref.sum())
    return 1.0 if denom == 0 else 2.0 * int((sil & ref).sum()) / denom


def prepare_case(
    cta: Volume,
    dsa: Mapping[str, DSARun],
    *,
    cranium_mask: Volume | None = None,
    segmentation: Volume | None = None,
    dsa_masks: Mapping[str, np.ndarray] | None = None,
    tto_px: int = TTO_PX_CPU,
    model_clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES,
    work_spacing_mm: float | None = None,
    monitor: Monitor | None = None,
) -> PreparedCase:
    """Masks and render volume of the CTA (HU), preprocessed PA / lateral runs (docs/conventions.md 5;
    TTO targets at ``tto_px``, the networks' images clipped to ``model_clip_percentiles``).

    A CTA finer than ``render.volume.RENDER_GRID_MM`` is rendered, and its masks made, on its block means (given
    masks: the blocks they fill at least half), in the CTA's own centred frame. Missing masks are computed from the
    CTA when first rendered (``geopose.cta.masks``); the vessel mask is then an approximation (a contrast threshold,
    its arteries kept by a classifier; empty for a CT without contrast) and ``labels_source`` says which, once it is
    computed. The
    'pa' run must look PA and the 'lat' run lateral by their primary angles.
    """
    monitor = monitor or Monitor()
    check_view_keys(dsa)
    for name, vol in (("cranium mask", cranium_mask), ("segmentation", segmentation)):
        if vol is not None and vol.array.shape != cta.array.shape:
            raise InputError(
                f"the {name} grid {vol.shape_ijk} differs from the CTA grid {cta.shape_ijk}: resample it onto the CTA first"
            )
    source = {
        "cranium": "given" if cranium_mask is not None else "computed from the CTA (bone threshold, closing, largest component, filled)",
        "vessels": "given segmentation" if segmentation is not None
        else "computed from the CTA (no segmentation given)",
    }

    def computed_vessels() -> Volume:
        mask = vessel_mask_from_cta(grid)
        source["vessels"] = f"computed from the CTA (no segmentation given): {mask.metadata['method']}"
        if "artery_classifier_sha256" in mask.metadata:
            source["artery_classifier_sha256"] = mask.metadata["artery_classifier_sha256"]
        return mask

    monitor.step("prepare", 0.0, "CTA")
    factors = render_factors(cta.spacing_mm)
    grid = cta.shrunk(factors)  # the CTA as rendered: itself unless finer than RENDER_GRID_MM

    def on_grid(mask: Volume) -> Volume:
        """A label volume on the CTA grid on the render grid: the whole blocks it fills at least half."""
        if grid is cta:
            return mask
        k, j, i = (n * f for n, f in zip(grid.array.shape, factors[::-1]))
        return grid.like(coarse_mask(np.asarray(mask.array[:k, :j, :i]) > 0, factors).astype(np.uint8))

    cranium = (lambda: on_grid(cranium_mask)) if cranium_mask is not None else (lambda: cranium_mask_from_cta(grid))
    vessels = (lambda: on_grid(segmentation)) if segmentation is not None else computed_vessels
    volume = RenderVolume(grid, {"cranium": cranium, "vessels": vessels}, finest_spacing_mm=work_spacing_mm,
                          scale=None if grid is cta else DensityScale.of(cta.array), centred_to_ras=cta.centred_to_ras)
    prepared: dict[str, PreparedDSA] = {}
    for i, key in enumerate(VIEW_KEYS):
        monitor.step("prepare", (i + 1) / 3, f"DSA {key.upper()}")
        kwargs = {"mask": dsa_masks[key]} if dsa_masks and key in dsa_masks else {}
        prepared[key] = preprocess_dsa(dsa[key], tto_px=tto_px, model_clip_percentiles=model_clip_percentiles, **kwargs)
    roles = (prepared["pa"].view_role, prepared["lat"].view_role)
    if roles != (PA_ROLE, LAT_ROLE):
        remedy = "swap them" if roles == (LAT_ROLE, PA_ROLE) else f"give a {'lateral' if roles[0] == PA_ROLE else 'PA'} run for the other view"
        raise InputError(
            f"the 'pa' run looks {roles[0]} and the 'lat' run {roles[1]} by their primary angles: {remedy}, or override the "
            "angle (primary_deg; CLI --pa-primary-deg / --lat-primary-deg) if the tags are wrong"
        )
    return PreparedCase(cta, volume, source, prepared)
