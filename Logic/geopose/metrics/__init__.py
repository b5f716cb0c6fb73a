"""Image, vessel and pose metrics: (multiscale) NCC, Dice, mPCD, clDice, pose errors.

``measures.py`` holds them in torch / numpy as each needs; ``numpy_similarity.py``
the NCC family in numpy for the torch-free inference path.
"""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "measures": (
            "ncc", "local_ncc", "mncc", "generalized_dice_loss", "MPCD", "mpcd", "mask_points", "skeletonize",
            "cldice", "PoseErrors", "pose_errors", "double_geodesic_mm", "view_accuracy",
        ),
    },
)
