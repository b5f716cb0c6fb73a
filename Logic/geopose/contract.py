"""The geometry and model contract shared with the published GeoPose models.

Every number that fixes what a pose, an image or a checkpoint *means* is named
here once (see ``docs/conventions.md``). Units are in the names: ``_MM`` for
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

# ------------------------------------------------------ inference schedules
GREEDY_MAX_PROPOSALS: Final = 5
#: A rejected biplane Refine proposal is tried once more, its move scaled by this, before the loop stops.
GREEDY_RETRY_FRACTION: Final = 0.5
#: The similarity search after biplane greedy Refine (``register/search.py``), coarse to fine: (step in mm
#: of isocentre shift and deg of turn about a view's central ray, pixels per side of the images scored;
#: None: the models' render size).
SEARCH_SCHEDULE: Final = ((4.0, 64), (2.0, 64), (1.0, None))
TTO_ITERATIONS: Final = 25
TTO_MAX_LR: Final = 1e-2
TTO_WARMUP_FRACTION: Final = 0.3
TTO_DIV_FACTOR: Final = 25.0
#: The OneCycle's last learning rate as a share of its peak: the paper's (PyTorch's default
#: ``final_div_factor`` 1e4, so 1 / (25 x 1e4)) and the patient-pose schedule's (experiments/tto_schedule/tto_schedule.md).
PAPER_TTO_FINAL_LR_FRACTION: Final = 1.0 / (TTO_DIV_FACTOR * 1e4)
TTO_FINAL_LR_FRACTION: Final = 0.1
TTO_TRANSLATION_SCALE_MM: Final = 200.0
TTO_NCC_WEIGHT: Final = 0.5
#: Ours: the objective's fitted silhouette (``register.objective.fit_like_target``) models the MAP's
#: brightness as a + b u + c exp(k u), u the DRR over its 99.5th percentile inside the DSA mask: quantum
#: noise (log domain) has an sd growing like exp(attenuation / 2), and the thickest head path attenuates
#: about e^-4, so k = 2 (experiments/tto_objective/silhouette.md).
SILHOUETTE_NOISE_EXPONENT: Final = 2.0
SILHOUETTE_NORM_PERCENTILE: Final = 99.5
BIPLANAR_WEIGHT: Final = 0.1

# ------------------------------------------------------- DSA preprocessing
MAP_CLIP_PERCENTILES: Final = (25.0, 75.0)
#: Ours, not the paper's: the vessel image (bolus-weighted mean of the frames) keeps the percentiles (over the
#: DSA cranium mask) between which the opacified vessels stand out of the noise (experiments/tto_objective/objective.md).
VESSEL_CLIP_PERCENTILES: Final = (90.0, 99.9)
#: Ours: the vessel image averages the frames weighted by the run's own bolus curve (a temporal matched
#: filter, ``dsa.preprocess.bolus_weighted_mean``), the curve read from the pixels whose temporal mean is at
#: or above this percentile over the DSA cranium mask (experiments/tto_objective/objective_real_heads.md).
BOLUS_PIXEL_PERCENTILE: Final = 98.0
#: Ours: which of the CTA's vessels the runs show opacified (``register/opacified.py``). A vessel voxel is
#: kept when, in every view with a vessel image, that image (blurred by ``OPACIFIED_BLUR_PX`` at the TTO
#: size, scaled to max 1) reaches ``OPACIFIED_THRESHOLD`` where the voxel projects; when fewer than
#: ``OPACIFIED_MIN_FRACTION`` of the voxels pass, the pose is taken as too far off and all are kept.
OPACIFIED_BLUR_PX: Final = 2.0
OPACIFIED_THRESHOLD: Final = 0.02
OPACIFIED_MIN_FRACTION: Final = 0.05
#: A TTO run continues with the opacified vessels only when its patient pose places the CTA's vessels
#: within this mean distance (mm) of where the selection was read; a farther run keeps all of them
#: (they guide a far start better).
OPACIFIED_NEAR_MM: Final = 5.0
BILATERAL_SPATIAL_SIGMA_PX: Final = 11.0
BILATERAL_RANGE_SIGMA: Final = 11.0
