"""Plausibility bounds of every input and option, named once.

Each bound is a closed interval ``(lo, hi)`` in the unit its name carries. Readers,
the options type and the Slicer panel check against these; :func:`check_range`
raises :class:`~geopose.errors.InputError` with the name, the value, the bound and
the remedy.
"""

from __future__ import annotations

import math
from typing import Final

from .errors import InputError

__all__ = [
    "REFINE_STEPS", "ITERATIONS", "TTO_PX", "RENDER_PX", "WORK_SPACING_MM", "CLIP_PERCENTILE",
    "check_range", "check_int",
]

# ---------------------------------------------------------------- options
#: Greedy refinement proposals per view.
REFINE_STEPS: Final = (0, 20)
#: Test-time optimisation steps.
ITERATIONS: Final = (0, 2000)
#: TTO image size (pixels along the detector's longer side).
TTO_PX: Final = (32, 1024)
#: Network-input render size (pixels along a side) before resizing to the model detector.
RENDER_PX: Final = (32, 512)
#: Voxel size (mm) of the working copy of the CTA the renderers sample.
WORK_SPACING_MM: Final = (0.25, 4.0)
#: Intensity clip percentiles of a MAP.
CLIP_PERCENTILE: Final = (0.0, 100.0)


def check_range(name: str, value: float, bound: tuple[float, float], remedy: str = "") -> float:
    """``value`` as a float if finite and within ``bound``, else an :class:`InputError`."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}{'; ' + remedy if remedy else ''}") from None
    lo, hi = bound
    if not math.isfinite(v) or not lo <= v <= hi:
        raise InputError(f"{name} = {value!r} is outside the plausible range {lo:g}..{hi:g}{'; ' + remedy if remedy else ''}")
    return v


def check_int(name: str, value: object, bound: tuple[int, int], remedy: str = "") -> int:
    """``value`` if it is a whole number (not a bool, not a fraction) within ``bound``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not value.is_integer()):
        raise InputError(f"{name} must be a whole number, got {value!r}{'; ' + remedy if remedy else ''}")
    check_range(name, value, bound, remedy)
    return int(value)
