"""Training GeoPose-Init and GeoPose-Refine on a canonicalised CTA population (paper section 3).

``canonical`` aligns CTAs to a template; ``population`` builds and caches the
density/label channels; ``poses``, ``augment`` and ``losses`` implement the
recipe; ``trainer`` runs it (CPU, CUDA, torchrun/DDP); ``evaluate`` measures
held-out errors; ``manifest`` writes and verifies ``Resources/Models/manifest.json``.
"""

from .augment import augment
from .canonical import Alignment, align_to_template, nearest_rotation, resample_to_template, rigid_error
from .population import TrainingSubject, folder_population, load_population, phantom_population, save_population
from .trainer import TrainConfig, train

__all__ = [
    "Alignment",
    "TrainConfig",
    "TrainingSubject",
    "align_to_template",
    "augment",
    "folder_population",
    "load_population",
    "nearest_rotation",
    "phantom_population",
    "resample_to_template",
    "rigid_error",
    "save_population",
    "train",
]
