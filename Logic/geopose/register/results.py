"""The in-memory results of a registration (no PyTorch).

Every pose is a camera-to-world ``(4, 4)`` float64 numpy array in the centred native
CTA frame (mm), whichever engine computed it. ``record.py`` turns a
:class:`CaseRegistration` into JSON.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..dsa import PreparedDSA
from ..options import RegistrationOptions
from ..volume import Volume
from .quality import Quality

if TYPE_CHECKING:
    from ..render.renderer import Renderer
    from .bound import BoundedMove
    from .evidence import ViewEvidence
    from .mirror import MirrorTest
    from .pairing import PairingTest
    from .opacified import VesselSelection
    from .tto import TTOResult
    from .vessel_image import VesselImageChoice

__all__ = ["Calibration", "InitEstimate", "Proposal", "RefineTrace", "SearchTrace", "ViewOutcome", "Registration",
           "CaseRegistration"]


@dataclass(frozen=True)
class Calibration:
    """Projection-space calibration: ``frame_transfer`` maps canonical to native poses (centred
    frames, mm); ``image`` is the PA calibration DRR ``(1, 1, 256, 256)``."""

    calibration_pose: np.ndarray
    predicted_canonical: np.ndarray
    frame_transfer: np.ndarray
    image: np.ndarray

    def to_native(self, pose_canonical: np.ndarray) -> np.ndarray:
        return self.frame_transfer @ pose_canonical


@dataclass(frozen=True)
class InitEstimate:
    """Calibrated Init output for one DSA view: native and canonical pose, the view label used,
    the view logits ``(3,)`` and the label the network itself chose (PA/lateral from metadata)."""

    pose_native: np.ndarray
    pose_canonical: np.ndarray
    view: int
    logits: np.ndarray
    network_view: int


@dataclass(frozen=True)
class Proposal:
    pose: np.ndarray
    mncc: float
    accepted: bool


@dataclass(frozen=True)
class RefineTrace:
    """Greedy refinement of one view: start and final pose with their mNCC, every proposal."""

    start_pose: np.ndarray
    start_mncc: float
    pose: np.ndarray
    mncc: float
    proposals: tuple[Proposal, ...] = ()

    @property
    def accepted(self) -> int:
        return sum(p.accepted for p in self.proposals)


@dataclass(frozen=True)
class SearchTrace:
    """The similarity search of one patient pose (``search.py``): start and end patient pose
    ``(4, 4)`` with the views' mean mNCC, the moves kept ``(parameter, step)`` in order, and how
    many poses were scored."""

    start_pose: np.ndarray
    start_mncc: float
    patient_pose: np.ndarray
    mncc: float
    moves: tuple[tuple[str, float], ...] = ()
    evaluations: int = 0


@dataclass(frozen=True)
class ViewOutcome:
    """Everything one view went through. ``init_pose`` is the pose after the Init stage: the
    view's own calibrated Init, or, registering one patient pose, the fused one; ``search_pose``
    the pose after the similarity search (None: it did not run); ``evidence`` the objective's terms at
    the final pose (``evidence.py``)."""

    key: str
    prepared: PreparedDSA
    init: InitEstimate
    init_pose: np.ndarray
    refine: RefineTrace
    final_pose: np.ndarray
    final_mncc: float
    silhouette_dice: float
    quality: Quality
    search_pose: np.ndarray | None = None
    evidence: "ViewEvidence | None" = None

    @property
    def stage_poses(self) -> dict[str, np.ndarray]:
        searched = {} if self.search_pose is None else {"search": self.search_pose}
        return {"init": self.init_pose, "refine": self.refine.pose, **searched, "final": self.final_pose}


@dataclass(frozen=True)
class Registration:
    """How the case was registered: ``mode`` ``biplane-rigid`` (one patient pose ``X``, the camera
    poses ``X @ A_v``; ``rig`` holds the ``A_v`` from the DICOM angles) or ``independent views``;
    the candidate starts with their objective (``starts``), the TTO run from each distinct start
    (``tto_runs``; those not among the tournament's finalists stopped after the coarse steps) with
    the finalists' final objective (``tto_objective``), the start the result came from
    (``chosen_start``); the opacified vessels the TTO read (at the networks' estimate, or after its coarse steps)
    (``vessel_selection``, ``opacified.py``; None: not read), by which alone ``tto_objective``
    compares the finalists; the consistency ``checks`` of the two views; the start of the
    greedy Refine that won (``refine_start``, :func:`.starts.refine_starts`) with every start's
    final mean mNCC (``refine_starts``); the similarity search after greedy Refine (``search``;
    None: it did not run); ``vessel_evidence``: whether the CTA's vessel mask held any vessel; ``bound``: without
    vessel evidence, the bounded move from the DICOM angles (``bound.py``); ``mirror``: the mirrored-CTA test
    (``mirror.py``; None: not run); ``pairing``: the precision of the vessel fit at the TTO's result, which a wrong
patient's CTA lacks (``pairing.py``; None: not run); ``kept_learned``: why the networks' estimate was kept over the TTO's result
    ("": it was not; ``trust.py``); ``vessel_images``: per view, which of the run's vessel images the objective
    compared (``vessel_image.py``; empty: the bolus-weighted ones, not chosen)."""

    mode: str
    rig: dict[str, np.ndarray] = field(default_factory=dict)
    patient_pose: np.ndarray | None = None
    starts: dict[str, float] = field(default_factory=dict)
    chosen_start: str = ""
    tto_runs: dict[str, "TTOResult"] = field(default_factory=dict)
    tto_objective: dict[str, float] = field(default_factory=dict)
    vessel_selection: "VesselSelection | None" = None
    checks: dict = field(default_factory=dict)
    refine_start: str = ""
    refine_starts: dict[str, float] = field(default_factory=dict)
    search: SearchTrace | None = None
    vessel_evidence: bool = True
    bound: "BoundedMove | None" = None
    mirror: "MirrorTest | None" = None
    pairing: "PairingTest | None" = None
    kept_learned: str = ""
    vessel_images: dict[str, "VesselImageChoice"] = field(default_factory=dict)


@dataclass(frozen=True)
class CaseRegistration:
    """One registered case. ``renderer`` is the renderer that was used (it renders the CTA's
    channels for overlays and metrics); ``tto`` is None when no test-time optimisation ran;
    ``engine`` says which backend, device and render sizes were used; ``notes`` what the
    user should know (e.g. a skipped stage); ``work`` the rendering each stage did (``render/work.py``)."""

    cta: Volume
    labels_source: dict
    calibration: Calibration
    views: dict[str, ViewOutcome]
    tto: "TTOResult | None"
    runtimes_s: dict[str, float]
    options: RegistrationOptions
    engine: dict
    registration: Registration
    renderer: "Renderer" = field(repr=False)
    notes: list[str] = field(default_factory=list)
    work: dict[str, dict] = field(default_factory=dict)
