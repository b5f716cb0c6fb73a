"""The phantom world: procedural head CTAs with arteries, and synthetic DSA runs.

It is the demo's default data, the training population and the ground truth.
See ``subject`` for the frames, ``labels`` for the label values and ``dsa`` for
the acquisitions; ``real_head`` gives a real head CT a phantom's arteries.
"""

from . import labels
from .real_head import with_arteries
from .subject import CANONICAL_FOV_MM, Subject, make_subject

__all__ = ["CANONICAL_FOV_MM", "Subject", "labels", "make_subject", "with_arteries"]
