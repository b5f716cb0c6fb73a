"""DRR rendering: HU->density, label channels, the differentiable cone-beam renderer."""

from .density import hu_to_density, label_channels
from .drr import DRR

__all__ = ["DRR", "hu_to_density", "label_channels"]
