"""DRR rendering: HU->density, label channels, the differentiable cone-beam renderer."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "density": ("hu_to_density", "label_channels"),
        "drr": ("DRR",),
    },
)
