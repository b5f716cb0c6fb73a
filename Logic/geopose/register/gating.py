"""The similarity-gated refinement rule of paper section 2.3.2, independent of the array library.

Each proposal ``T_new = propose(T, image)`` is rendered and scored; it is accepted
only if the score strictly increases, and the loop stops at the first rejection or
after ``max_proposals``. ``refine.py`` (torch) and ``numpy_pipeline.py`` supply the
renderer, the score (mNCC against the target) and the network's proposal.
"""

from __future__ import annotations

from typing import Any, Callable

from .progress import Monitor
from .results import Pose, Proposal, RefineTrace

__all__ = ["gated_refinement"]


def gated_refinement(
    pose: Pose,
    render: Callable[[Pose], Any],
    score: Callable[[Any], float],
    propose: Callable[[Pose, Any], Pose],
    max_proposals: int,
    monitor: Monitor | None = None,
) -> RefineTrace:
    """Refine ``pose`` by accepted proposals; ``render(pose)`` -> image, ``score(image)`` -> float,
    ``propose(pose, image)`` -> candidate pose."""
    monitor = monitor or Monitor()
    current = pose
    image = render(current)
    current_score = score(image)
    trace = RefineTrace(pose, current_score, pose, current_score)
    for k in range(max_proposals):
        monitor.step("refine", k / max_proposals, f"proposal {k + 1}/{max_proposals}")
        candidate = propose(current, image)
        cand_image = render(candidate)
        cand_score = score(cand_image)
        accepted = cand_score > current_score
        trace.proposals.append(Proposal(candidate, cand_score, accepted))
        if not accepted:
            break
        current, image, current_score = candidate, cand_image, cand_score
    trace.pose, trace.mncc = current, current_score
    monitor.step("refine", 1.0, f"{trace.accepted} of {len(trace.proposals)} proposals accepted")
    return trace
