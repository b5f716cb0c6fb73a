"""How much rendering a stage did: renders, rays and ray points (trilinear samples per channel), counted by
both kernels while a :func:`counting` block is open in the calling thread (a ``contextvars`` context, so
registrations in other threads count apart).

A rendering stage's seconds divided by its ray points (``ns_per_point``) is the machine's speed on this
work: about the same on every case of one machine; a case that is slower at the same ``ns_per_point``
did more work (a finer CTA level, a larger detector, more steps), one that is slower per point ran on a
busier or slower machine. Stages whose time is mostly not rendering (calibration: the CTA's masks;
Refine: the networks) show a large ``ns_per_point``; compare them case to case only.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Iterator

__all__ = ["RenderWork", "counting", "count"]


@dataclass
class RenderWork:
    """Renders (one pose on one detector), rays (pixels) and ray points (rays x samples per ray x channels)."""

    renders: int = 0
    rays: int = 0
    points: int = 0

    def as_dict(self, seconds: float) -> dict:
        return {"renders": self.renders, "rays": self.rays, "ray_points": self.points,
                "ns_per_point": round(1e9 * seconds / self.points, 3) if self.points else None}


_current: ContextVar[RenderWork | None] = ContextVar("geopose_render_work", default=None)


def count(renders: int, rays: int, samples_per_ray: int, channels: int) -> None:
    """Add one kernel call's work to the open :func:`counting` block (none open: nothing)."""
    work = _current.get()
    if work is not None:
        work.renders += renders
        work.rays += rays
        work.points += rays * samples_per_ray * channels


@contextmanager
def counting() -> Iterator[RenderWork]:
    """Count the rendering done in this thread until the block closes."""
    work = RenderWork()
    token = _current.set(work)
    try:
        yield work
    finally:
        _current.reset(token)
