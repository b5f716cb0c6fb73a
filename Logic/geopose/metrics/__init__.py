"""Image similarity and registration metrics.

``similarity.py``: the NCC family in numpy (scores: the refinement gate, the final
mNCC, the benchmark); ``losses.py``: the same similarities and the Dice loss in torch,
differentiable (the TTO objective, training); ``measures.py``: mPCD, clDice, pose
errors and view accuracy (numpy).
"""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "similarity": ("ncc", "local_ncc", "mncc"),
        "losses": ("ncc_similarity", "local_ncc_similarity", "mncc_similarity", "generalized_dice_loss"),
        "measures": (
            "MPCD", "mpcd", "mask_points", "skeletonize", "cldice", "PoseErrors", "pose_errors", "pose_error_components",
            "double_geodesic_mm",
            "view_accuracy",
        ),
    },
)
