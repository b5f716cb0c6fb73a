"""The paper's training recipe (docs/conventions.md section 6), named once.

Units: rad for rotations, mm for translations. These are training choices, not
part of the geometry/model contract (``geopose.contract``).
"""

from __future__ import annotations

from typing import Final

#: Probability that a sampled training view is PA (the rest is lateral, side 50/50).
PA_PROBABILITY: Final = 0.5
#: Gaussian noise added to the isopose's Euler ZYX angles (rad) and rotated-frame translation (mm).
INIT_ROTATION_SD_RAD: Final = (0.2, 0.2, 0.2)
INIT_TRANSLATION_SD_MM: Final = (25.0, 75.0, 25.0)
#: Refine perturbation sd (axis-angle rad, translation mm) per view family.
REFINE_LAT_ROTATION_SD_RAD: Final = (0.15, 0.11, 0.15)
REFINE_LAT_TRANSLATION_SD_MM: Final = (4.0, 36.0, 5.0)
REFINE_PA_ROTATION_SD_RAD: Final = (0.07, 0.05, 0.11)
REFINE_PA_TRANSLATION_SD_MM: Final = (3.0, 31.0, 5.0)
#: Calibrated Refine perturbations are kept within these factors of the recipe's sd.
CALIBRATION_CLAMP: Final = (0.5, 2.0)

#: Init loss weights: -mNCC, geodesics (log-SE3 + double), vessel Dice + projected fiducials, view CE.
W_MNCC: Final = 1.0
W_GEODESIC: Final = 0.01
W_VESSEL: Final = 0.1
W_VIEW: Final = 1.0

#: Optimiser (AdamW + cosine) and batch recipe.
LEARNING_RATE: Final = 1.5e-4
WEIGHT_DECAY: Final = 1e-5
BATCH_SIZE: Final = 4
INIT_ACCUMULATION: Final = 8
REFINE_ACCUMULATION: Final = 4

#: Augmentation probabilities and ranges (each p = 1/3 unless noted).
AUG_P: Final = 1.0 / 3.0
CLAHE_CLIP: Final = (1.0, 10.0)
CLAHE_TILES: Final = 8
CLAHE_BINS: Final = 64
GAMMA_RANGE: Final = (0.7, 1.8)
NOISE_SD: Final = 0.1
BILATERAL_SPATIAL_PX: Final = (1.0, 15.0)
#: Bilateral window radius (px) used for the augmentation; wider sigmas are truncated.
BILATERAL_RADIUS_PX: Final = 3
BILATERAL_RANGE_SD: Final = (0.05, 0.3)
SHARPNESS_RANGE: Final = (0.5, 2.0)
PLASMA_ROUGHNESS: Final = (0.1, 0.5)
PLASMA_BRIGHTNESS: Final = 0.3
PLASMA_CONTRAST: Final = 0.5
ERASE_FRACTION: Final = (0.02, 0.15)
COLLIMATION_MAX_PX: Final = 10
#: MAP-likeness (phantom DRR -> DSA MAP look): probability, skull-rim gain, subtraction-noise sd.
MAP_LIKE_P: Final = 0.5
SKULL_RIM_GAIN: Final = (0.3, 1.0)
SUBTRACTION_NOISE_SD: Final = (0.02, 0.1)
#: The DSA MAP look (``augment.dsa_map``; ours): noise sd ~ exp(kappa * min-max line integral), the
#: relative spread of its frame maximum, the vessels' gain against the noise level, the head
#: mask's line-integral level, the quantile where the stored range saturates, and the share of
#: training images that get it.
DSA_NOISE_KAPPA: Final = (1.5, 2.5)
DSA_NOISE_SPREAD: Final = 0.35
DSA_VESSEL_GAIN: Final = (0.5, 3.0)
DSA_MASK_LEVEL: Final = (0.05, 0.2)
DSA_SATURATION_QUANTILE: Final = (0.8, 0.995)
DSA_LOOK_P: Final = 0.5
#: Input clip of the networks trained here (recorded in the model file and the manifest):
#: mild, so the MAP's inner structure survives (experiments/init_depth/init_depth.md).
INPUT_CLIP_PERCENTILES: Final = (2.0, 98.0)
