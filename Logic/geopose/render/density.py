"""HU -> DRR density (CONVENTIONS section 3) and label-split channels, numpy or torch."""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping, Sequence, TypeVar

import numpy as np

from .. import contract as C

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["hu_to_density", "label_channels"]

Array = TypeVar("Array", np.ndarray, "Tensor")


def hu_to_density(hu: Array, bone_factor: float = C.BONE_FACTOR) -> Array:
    """Density in [0, 1] (float32) from HU: air (<= HU_AIR_MAX) set to the soft-tissue minimum,
    bone (> HU_BONE_MIN) scaled by ``bone_factor``, then min-max over the volume.
    Answers in the kind it is given (numpy array or torch tensor)."""
    if not isinstance(hu, np.ndarray):
        import torch

        return torch.as_tensor(hu_to_density(hu.detach().cpu().numpy(), bone_factor), device=hu.device)
    x = hu.astype(np.float32)
    soft = (x > C.HU_AIR_MAX) & (x <= C.HU_BONE_MIN)
    floor = np.float32(x[soft].min() if soft.any() else C.HU_AIR_MAX)
    x = np.where(x <= C.HU_AIR_MAX, floor, x)
    x = np.where(x > C.HU_BONE_MIN, x * np.float32(bone_factor), x)
    lo, hi = x.min(), x.max()
    return ((x - lo) / max(float(hi - lo), 1e-12)).astype(np.float32)


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
