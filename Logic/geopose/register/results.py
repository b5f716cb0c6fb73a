"""The in-memory results of a registration, whichever path produced them (no PyTorch).

The torch pipeline fills them with tensors, the numpy pipeline with numpy arrays:
poses are camera-to-world ``(1, 4, 4)`` (or ``(4, 4)``) in the centred native CTA
frame (mm). ``record.py`` turns a :class:`CaseRegistration` into JSON.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Union

import numpy as np

from .. import contract as C
from ..dsa import PreparedDSA
from ..dsa import check_clip_percentiles
from ..volume import Volume
from .quality import Quality

if TYPE_CHECKING:
    from torch import Tensor

    from .tto import TTOResult

__all__ = ["Pose", "RegistrationOptions", "Calibration", "InitEstimate", "Proposal", "RefineTrace", "ViewOutcome", "CaseRegistration"]

#: A pose or batch of poses: a torch tensor (torch pipeline) or a numpy array (numpy pipeline).
Pose = Union["Tensor", np.ndarray]


@dataclass
class RegistrationOptions:
    """Knobs of a registration (defaults follow the paper)."""

    refine_steps: int = C.GREEDY_MAX_PROPOSALS
    iterations: int = C.TTO_ITERATIONS
    tto_px: int | None = None  # None: the model resolution on a GPU, half of it on a CPU
    biplanar: bool = False
    device: str = "auto"
    #: Percentiles the networks' MAP is clipped to (the TTO target keeps CONVENTIONS 5).
    model_clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES

    def __post_init__(self) -> None:
        self.model_clip_percentiles = check_clip_percentiles(self.model_clip_percentiles)


@dataclass
class Calibration:
    """``frame_transfer``: canonical -> native (centred frames, mm); ``image`` the PA calibration DRR."""

    calibration_pose: Pose
    predicted_canonical: Pose
    frame_transfer: Pose
    image: Any

    def to_native(self, pose_canonical: Pose) -> Pose:
        return self.frame_transfer @ pose_canonical


@dataclass
class InitEstimate:
    """Calibrated Init output for one DSA view."""

    pose_native: Pose
    pose_canonical: Pose
    view: int
    logits: Any


@dataclass
class Proposal:
    pose: Pose
    mncc: float
    accepted: bool


@dataclass
class RefineTrace:
    start_pose: Pose
    start_mncc: float
    pose: Pose
    mncc: float
    proposals: list[Proposal] = field(default_factory=list)

    @property
    def accepted(self) -> int:
        return sum(p.accepted for p in self.proposals)


@dataclass
class ViewOutcome:
    """Everything one view went through."""

    key: str
    prepared: PreparedDSA
    init: InitEstimate
    refine: RefineTrace
    final_pose: Pose
    final_mncc: float
    silhouette_dice: float
    quality: Quality

    @property
    def stage_poses(self) -> dict[str, Pose]:
        return {"init": self.init.pose_native, "refine": self.refine.pose, "final": self.final_pose}


@dataclass
class CaseRegistration:
    """One registered case. ``drr`` is the renderer that was used (torch ``DRR`` or
    ``NumpyDRR``); ``tto`` is None when no test-time optimisation ran."""

    cta: Volume
    labels: Volume
    labels_source: dict
    calibration: Calibration
    views: dict[str, ViewOutcome]
    tto: "TTOResult | None"
    runtimes_s: dict[str, float]
    device: str
    options: RegistrationOptions
    drr: Any = field(repr=False)
