"""The one carrier of registration settings: :class:`RegistrationOptions`.

Built by keyword everywhere (Python, the ``geopose`` command line, the benchmark,
the Slicer parameter node's defaults) and validated once, on construction; frozen,
so no caller's options are changed behind its back. Imports nothing beyond the
standard library (the Slicer module reads its defaults before the dependencies
are installed).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from . import contract as C
from . import limits as L
from .errors import InputError

__all__ = ["BACKENDS", "DEVICES", "RegistrationOptions", "check_clip_percentiles"]

#: ``torch``: torch renderer and networks; ``onnxruntime``: numpy renderer and the shipped
#: ONNX graphs (no PyTorch needed); ``auto``: torch when it imports, else onnxruntime.
BACKENDS = ("auto", "torch", "onnxruntime")
#: Where torch computes: ``auto`` takes CUDA when present.
DEVICES = ("auto", "cpu", "cuda")


def check_clip_percentiles(percentiles: Any) -> tuple[float, float]:
    """``(lo, hi)`` with ``0 <= lo < hi <= 100`` as floats, or an :class:`InputError` naming the rule."""
    try:
        lo, hi = (float(p) for p in percentiles)
    except (TypeError, ValueError):
        raise InputError(f"clip percentiles must be two numbers (lo, hi), got {percentiles!r}") from None
    if not L.CLIP_PERCENTILE[0] <= lo < hi <= L.CLIP_PERCENTILE[1]:
        raise InputError(f"clip percentiles ({lo:g}, {hi:g}) must satisfy 0 <= lo < hi <= 100, e.g. (2, 98) or "
                         f"docs/conventions.md 5's {C.MAP_CLIP_PERCENTILES}")
    return lo, hi


@dataclass(frozen=True)
class RegistrationOptions:
    """Every setting of one registration. ``None`` means "decided by the data": the
    models' manifest (``render_px``, ``model_clip_percentiles``), the device (``tto_px``)
    or the CTA (``work_spacing_mm``); the result record says what was used."""

    #: Engine: see :data:`BACKENDS`.
    backend: str = "auto"
    #: torch device: see :data:`DEVICES` (``cuda:N`` picks a GPU).
    device: str = "auto"
    #: Greedy refinement proposals per view (paper: 5).
    refine_steps: int = C.GREEDY_MAX_PROPOSALS
    #: Test-time optimisation steps (paper: 25; 0 skips it).
    iterations: int = C.TTO_ITERATIONS
    #: TTO image size, pixels along the detector's longer side (None: 256 on CUDA, 128 on a CPU).
    tto_px: int | None = None
    #: Pixels (per side) of the DRRs the networks see, before resizing to the 256 px model
    #: detector (None: each model's training size from its manifest).
    render_px: int | None = None
    #: Percentiles the networks' MAP is clipped to (None: each model's manifest, else
    #: docs/conventions.md 5); the TTO target always keeps docs/conventions.md 5.
    model_clip_percentiles: tuple[float, float] | None = None
    #: Voxel size (mm) of the working copy of the CTA the renderers sample (None: the
    #: CTA's own, coarsened where that is finer than the images need).
    work_spacing_mm: float | None = None
    #: Register each view on its own (the published pipeline) instead of one patient pose
    #: seen by both arms of the biplane system (their relative geometry from the DICOM angles).
    independent_views: bool = False
    #: After biplane greedy Refine, search the patient pose's shift and in-plane turns by the views'
    #: mNCC (``register/search.py``; ours, not the paper's). Ignored with ``independent_views``.
    search: bool = True
    #: Add the PA/lateral orthogonality term to the TTO objective (docs/conventions.md 5; independent views).
    biplanar: bool = False

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise InputError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        device = str(self.device)
        if device not in DEVICES and not (device.startswith("cuda:") and device[5:].isdigit()):
            raise InputError(f"device must be auto, cpu, cuda or cuda:N, got {self.device!r}")
        object.__setattr__(self, "device", device)
        ints = {
            "refine_steps": (L.REFINE_STEPS, "the paper uses 5"),
            "iterations": (L.ITERATIONS, "the paper uses 25; 0 skips the test-time optimisation"),
            "tto_px": (L.TTO_PX, "leave it unset for 256 on CUDA, 128 on a CPU"),
            "render_px": (L.RENDER_PX, "leave it unset for the models' training size"),
        }
        for name, (bound, remedy) in ints.items():
            if getattr(self, name) is not None:
                object.__setattr__(self, name, L.check_int(name, getattr(self, name), bound, remedy))
        if self.model_clip_percentiles is not None:
            object.__setattr__(self, "model_clip_percentiles", check_clip_percentiles(self.model_clip_percentiles))
        if self.work_spacing_mm is not None:
            object.__setattr__(
                self, "work_spacing_mm", L.check_range("work_spacing_mm", self.work_spacing_mm, L.WORK_SPACING_MM)
            )
        for name in ("independent_views", "search", "biplanar"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name} must be True or False, got {getattr(self, name)!r}")

    def replace(self, **changes: Any) -> "RegistrationOptions":
        """A copy with ``changes`` (validated like a new one)."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise InputError(f"unknown registration option(s) {', '.join(sorted(unknown))}; "
                             f"known: {', '.join(f.name for f in dataclasses.fields(self))}")
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
