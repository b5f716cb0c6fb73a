"""HU -> DRR density (docs/conventions.md section 3) and label-split channels, numpy or torch."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping, Sequence, TypeVar

import numpy as np

from .. import contract as C

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["DensityScale", "hu_to_density", "label_channels"]

Array = TypeVar("Array", np.ndarray, "Tensor")


#: Slices per block while scanning a volume for its density scale.
SCAN_SLICES = 32


@dataclass(frozen=True)
class DensityScale:
    """docs/conventions.md 3 for one volume: HU <= HU_AIR_MAX become ``floor_hu`` (its smallest soft-tissue
    value), HU > HU_BONE_MIN are multiplied by ``bone_factor``, then ``(hu' - lo_hu) / span_hu``."""

    floor_hu: float
    lo_hu: float
    span_hu: float
    bone_factor: float = C.BONE_FACTOR

    @classmethod
    def of(cls, hu: np.ndarray, bone_factor: float = C.BONE_FACTOR) -> "DensityScale":
        """The scale of a ``[k, j, i]`` HU volume, scanned block by block (no full-size temporaries)."""
        soft_min = tissue_min = math.inf
        top = -math.inf
        for k0 in range(0, hu.shape[0], SCAN_SLICES):
            x = np.asarray(hu[k0 : k0 + SCAN_SLICES], dtype=np.float32)
            tissue = x[x > C.HU_AIR_MAX]
            if tissue.size:
                tissue_min = min(tissue_min, float(tissue.min()))
                soft = tissue[tissue <= C.HU_BONE_MIN]
                if soft.size:
                    soft_min = min(soft_min, float(soft.min()))
            top = max(top, float(x.max()))
        floor = soft_min if math.isfinite(soft_min) else C.HU_AIR_MAX
        lo = min(floor, tissue_min * bone_factor if tissue_min > C.HU_BONE_MIN else tissue_min)
        hi = max(floor, top * bone_factor if top > C.HU_BONE_MIN else top)
        return cls(floor, lo, max(hi - lo, 1e-12), bone_factor)

    def apply(self, hu: np.ndarray) -> np.ndarray:
        """Density (float32, [0, 1] over the volume the scale came from) of HU values."""
        x = np.array(hu, dtype=np.float32)  # a copy: the steps below work in place
        np.copyto(x, np.float32(self.floor_hu), where=x <= C.HU_AIR_MAX)
        if self.bone_factor != 1.0:
            np.multiply(x, np.float32(self.bone_factor), out=x, where=x > C.HU_BONE_MIN)
        x -= np.float32(self.lo_hu)
        x /= np.float32(self.span_hu)
        return x


def hu_to_density(hu: Array, bone_factor: float = C.BONE_FACTOR) -> Array:
    """Density in [0, 1] (float32) from HU (:class:`DensityScale` of the whole volume).
    Answers in the kind it is given (numpy array or torch tensor)."""
    if not isinstance(hu, np.ndarray):
        import torch

        return torch.as_tensor(hu_to_density(hu.detach().cpu().numpy(), bone_factor), device=hu.device)
    return DensityScale.of(hu, bone_factor).apply(hu)


def label_channels(
    density: Array, labels: Array | None, groups: Mapping[str, Sequence[int]] | None
) -> tuple[Array, list[str]]:
    """Stack ``(C, K, J, I)``: channel 0 = total density, then density inside each label group
    (numpy or torch, as given)."""
    channels, names = [density], ["total"]
    if labels is not None and groups:
        if labels.shape != density.shape:
            raise ValueError(f"label map shape {tuple(labels.shape)} differs from the CTA {tuple(density.shape)}")
        for name, values in groups.items():
            if isinstance(labels, np.ndarray):
                mask = np.isin(labels, list(values))
            else:
                import torch

                mask = torch.isin(labels, torch.as_tensor(list(values), dtype=labels.dtype, device=labels.device))
            channels.append(density * mask)
            names.append(name)
    if isinstance(density, np.ndarray):
        return np.stack(channels), names
    import torch

    return torch.stack(channels), names
