"""HU -> DRR density (CONVENTIONS section 3) and label-split channels."""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .. import contract as C

__all__ = ["hu_to_density", "label_channels"]


def hu_to_density(hu: np.ndarray | Tensor, bone_factor: float = C.BONE_FACTOR) -> np.ndarray | Tensor:
    """Density in [0, 1] from HU: air (<= HU_AIR_MAX) set to the soft-tissue minimum,
    bone (> HU_BONE_MIN) scaled by ``bone_factor``, then min-max over the volume."""
    is_np = isinstance(hu, np.ndarray)
    x = torch.as_tensor(hu).float()
    soft = (x > C.HU_AIR_MAX) & (x <= C.HU_BONE_MIN)
    floor = x[soft].min() if bool(soft.any()) else torch.tensor(C.HU_AIR_MAX)
    x = torch.where(x <= C.HU_AIR_MAX, floor, x)
    x = torch.where(x > C.HU_BONE_MIN, x * bone_factor, x)
    lo, hi = x.min(), x.max()
    x = (x - lo) / (hi - lo).clamp_min(1e-12)
    return x.numpy() if is_np else x


def label_channels(
    density: Tensor, labels: Tensor | None, groups: Mapping[str, Sequence[int]] | None
) -> tuple[Tensor, list[str]]:
    """Stack ``(C, K, J, I)``: channel 0 = total density, then density inside each label group."""
    channels, names = [density], ["total"]
    if labels is not None and groups:
        if labels.shape != density.shape:
            raise ValueError(f"label map shape {tuple(labels.shape)} differs from the CTA {tuple(density.shape)}")
        for name, values in groups.items():
            mask = torch.isin(labels, torch.as_tensor(list(values), dtype=labels.dtype, device=labels.device))
            channels.append(density * mask)
            names.append(name)
    return torch.stack(channels), names
