"""Progress reporting, cancellation and the result delivered before the end, shared by every registration stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Optional

import numpy as np

#: ``progress(stage, fraction_done, message)``; fraction in [0, 1] within the stage.
ProgressCallback = Callable[[str, float, str], None]
#: Returns True when the user asked to stop.
CancelCheck = Callable[[], bool]




@dataclass(frozen=True)
class Preliminary:
    """A pose per view the registration has reached before it ends, for a front end to show meanwhile.

    ``stage``: what made it (``"estimate"``: the networks' estimate, before the test-time optimisation);
    ``poses``: ``{view: (4, 4)}`` float64 camera-to-world in the centred native CTA frame (mm), as the final
    result's; ``elapsed_s``: seconds since the registration started."""

    stage: str
    poses: Mapping[str, np.ndarray]
    elapsed_s: float


#: ``preliminary(result)``: called once per :class:`Preliminary` result, on the registration's thread.
PreliminaryCallback = Callable[[Preliminary], None]


def hand_over_estimate(preliminary: Optional[PreliminaryCallback], poses: Mapping[str, np.ndarray], elapsed_s: float) -> None:
    """Give ``preliminary`` (when there is one) the networks' estimate ``poses`` (copied) as a :class:`Preliminary`."""
    if preliminary is not None:
        preliminary(Preliminary("estimate", {key: np.array(pose) for key, pose in poses.items()}, elapsed_s))


class RegistrationCancelled(RuntimeError):
    """Raised inside a stage when the cancel hook returns True."""


@dataclass
class Monitor:
    """Bundles the optional progress callback and cancel hook for a stage."""

    progress: Optional[ProgressCallback] = None
    cancel: Optional[CancelCheck] = None

    def step(self, stage: str, fraction: float, message: str = "") -> None:
        if self.cancel is not None and self.cancel():
            raise RegistrationCancelled(f"registration cancelled during {stage}")
        if self.progress is not None:
            self.progress(stage, min(max(fraction, 0.0), 1.0), message)

    def part(self, index: float, count: int, label: str, width: float = 1.0) -> "Monitor":
        """The monitor of part ``index`` of ``count`` equal parts of a stage (``width`` parts wide): fractions mapped
        into that share, messages prefixed with ``label``; the same cancel hook."""
        if self.progress is None:
            return Monitor(None, self.cancel)
        outer = self.progress
        return Monitor(lambda stage, f, m: outer(stage, (index + width * min(max(f, 0.0), 1.0)) / count, f"{label}: {m}"),
                       self.cancel)


class ConsoleProgress:
    """A text progress bar per stage on a stream (``stderr`` by default)."""

    def __init__(self, stream=None, width: int = 28):
        import sys

        self.stream = stream or sys.stderr
        self.width = width
        self.stage = None

    def __call__(self, stage: str, fraction: float, message: str) -> None:
        if stage != self.stage and self.stage is not None:
            self.stream.write("\n")
        self.stage = stage
        filled = int(round(fraction * self.width))
        bar = "#" * filled + "-" * (self.width - filled)
        self.stream.write(f"\r{stage:<12s} [{bar}] {fraction * 100:5.1f}% {message[:50]:<50s}")
        if stage == "done":
            self.stream.write("\n")
            self.stage = None
        self.stream.flush()

    def finish(self) -> None:
        """End an unfinished bar's line (a stage stopped by an error), so the next message starts a line."""
        if self.stage is not None:
            self.stream.write("\n")
            self.stream.flush()
            self.stage = None
