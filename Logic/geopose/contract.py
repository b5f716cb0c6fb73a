"""The geometry and model contract shared with the published GeoPose models.

Every number that fixes what a pose, an image or a checkpoint *means* is named
here once (see ``docs/conventions.md``); the registration's settings and tuning
live in the options tree (``options.py``) and the stage modules. Units are in the names: ``_MM`` for
millimetres, ``_RAD`` for radians, ``_DEG`` for degrees, ``_PX`` for pixels.
"""

from __future__ import annotations

import math
from typing import Final

# ---------------------------------------------------------------- view classes
VIEW_LAT_MINUS: Final = 0
VIEW_PA: Final = 1
VIEW_LAT_PLUS: Final = 2
VIEW_NAMES: Final = ("LAT-", "PA", "LAT+")
#: The view each view looks like in a left-right mirrored image (detector columns
#: reversed): a head is nearly symmetric, so a mirrored LAT+ image resembles a LAT- one.
MIRRORED_VIEW: Final = (VIEW_LAT_PLUS, VIEW_PA, VIEW_LAT_MINUS)
#: Euler ZYX first angle (about world z, superior) of each view's isopose.
VIEW_ANCHOR_RAD: Final = (-math.pi / 2, 0.0, math.pi / 2)
#: |PositionerPrimaryAngle| beyond which a view is lateral.
LATERAL_THRESHOLD_DEG: Final = 45.0

# ------------------------------------------------------------ isocentric pose
#: Source-to-isocentre distance of the isopose (t = (0, SOI, 0) in the rotated frame).
SOURCE_TO_ISOCENTER_MM: Final = 650.0
ISO_TRANSLATION_MM: Final = (0.0, SOURCE_TO_ISOCENTER_MM, 0.0)

# ------------------------------------------------------- model (K0) detector
MODEL_DETECTOR_PX: Final = 256
MODEL_PIXEL_SPACING_MM: Final = 1.2
MODEL_SDD_MM: Final = 1020.0

# ------------------------------------------------------ HU -> density (DRR)
HU_AIR_MAX: Final = -800.0
HU_BONE_MIN: Final = 350.0
BONE_FACTOR: Final = 1.0

# ------------------------------------------------------------- network heads
INIT_TRANSLATION_SCALE_MM: Final = 100.0
REFINE_ROTATION_SCALE_RAD: Final = (0.13, 0.10, 0.14)
REFINE_TRANSLATION_SCALE_MM: Final = (4.0, 33.0, 5.0)
VIEW_EMBEDDING_DIM: Final = 16

# ---------------------------------------------------------------- similarity
MNCC_PATCH_PX: Final = 13
#: Weight of the global NCC in mNCC; the local (patch) NCC gets the rest.
MNCC_GLOBAL_WEIGHT: Final = 0.5
NCC_EPS: Final = 1e-5

# ------------------------------------------------------- DSA preprocessing
MAP_CLIP_PERCENTILES: Final = (25.0, 75.0)
#: Ours, not the paper's: the vessel image (bolus-weighted mean of the frames) keeps the percentiles (over the
#: DSA cranium mask) between which the opacified vessels stand out of the noise (experiments/tto_objective/objective.md).
VESSEL_CLIP_PERCENTILES: Final = (90.0, 99.9)
#: Ours: the vessel image averages the frames weighted by the run's own bolus curve (a temporal matched
#: filter, ``dsa.preprocess.bolus_weighted_mean``), the curve read from the pixels whose temporal mean of fine
#: detail is at or above this percentile over the DSA cranium mask (experiments/tto_objective/objective_real_heads.md,
#: experiments/vessel_image/vessel_image.md).
BOLUS_PIXEL_PERCENTILE: Final = 98.0
BILATERAL_SPATIAL_SIGMA_PX: Final = 11.0
BILATERAL_RANGE_SIGMA: Final = 11.0
