"""Is the CTA mirrored left-right? The registration's result weighed against the mirrored hypothesis.

A CTA whose header swaps the patient's sides still fits the head's nearly symmetric silhouette,
but a one-sided injection's vessels then lie on the wrong side; one rigid patient pose cannot
fit both views' vessels, yet each view alone fits them partly, so the final pose's own numbers
do not tell it. The test builds the hypothesis: the CTA and its masks mirrored across the grid's
centre plane normal to the array axis nearest RAS x (left-right), optimised by a short TTO from
the registration's own patient pose. The result must fit the runs better by the objective
(``objective.py``, both views summed) than that, by at least :data:`MIRROR_LOSS_MARGIN`; otherwise
the sides are in doubt (validation phantom 6011: a correct CTA beat its mirror image by 0.146, the
same CTA with its sides swapped by -0.002). Needs PyTorch (the TTO) and a given vessel
segmentation: without vessels there is nothing to tell the sides by, and on a vessel mask computed
from the CTA (veins and bone included) correct CTAs of phantoms 6000, 6001 and 5001 beat their mirror
image by -0.04 to +0.01 only, and no variant of the test separates them
(experiments/mirror/mirror.md), so the test is not run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Mapping

import numpy as np

from ..dsa import PreparedDSA
from ..render.renderer import Renderer, TorchRenderer, make_renderer
from ..render.volume import RenderVolume
from ..volume import Volume
from .biplane import view_poses
from ..options import Objective, TTOSchedule
from .objective import pair_objective
from .progress import Monitor

__all__ = ["MIRROR_TTO_ITERATIONS", "MIRROR_LOSS_MARGIN", "MirrorTest", "mirrored_volume", "mirror_test"]

#: TTO steps of the mirrored hypothesis, from the registration's own patient pose.
MIRROR_TTO_ITERATIONS: Final = 12
#: The result must beat the mirrored hypothesis by this much (objective, both views summed) to pass.
MIRROR_LOSS_MARGIN: Final = 0.03


@dataclass(frozen=True)
class MirrorTest:
    """The objective (both views summed) of the result (``loss``) and of the mirrored CTA after its short
    TTO (``mirrored_loss``); ``margin`` = mirrored less result: below :data:`MIRROR_LOSS_MARGIN`, the
    mirrored CTA explains the runs about as well or better."""

    loss: float
    mirrored_loss: float

    @property
    def margin(self) -> float:
        return self.mirrored_loss - self.loss

    @property
    def mirrored(self) -> bool:
        return self.margin < MIRROR_LOSS_MARGIN

    def as_dict(self) -> dict:
        return {"loss": self.loss, "mirrored_loss": self.mirrored_loss, "margin": self.margin, "mirrored": self.mirrored,
                "iterations": MIRROR_TTO_ITERATIONS, "loss_margin": MIRROR_LOSS_MARGIN}


def _left_right_axis(cta: Volume) -> int:
    """The array axis (``[k, j, i]`` order) whose voxel direction is closest to RAS x."""
    x_component = np.abs(cta.ijk_to_ras[0, :3]) / np.asarray(cta.spacing_mm)
    return 2 - int(np.argmax(x_component))


def mirrored_volume(volume: RenderVolume) -> RenderVolume:
    """``volume``'s CTA and masks mirrored left-right (flipped along the array axis nearest RAS x, same
    header: a reflection across the grid's centre plane in the centred frame)."""
    axis = _left_right_axis(volume.cta)
    flip = lambda a: np.ascontiguousarray(np.flip(a, axis))  # noqa: E731
    cta = volume.cta.like(flip(volume.cta.array))
    masks = {name: cta.like(flip(volume.mask(name)).astype(np.uint8)) for name in ("cranium", "vessels")
             if volume.mask(name) is not None}
    return RenderVolume(cta, masks, finest_spacing_mm=volume.finest_spacing_mm)


def mirror_test(renderer: Renderer, views: Mapping[str, PreparedDSA], patient_pose: np.ndarray,
                rig: Mapping[str, np.ndarray], objective: Objective = Objective(), device: str = "cpu",
                monitor: Monitor | None = None) -> MirrorTest:
    """The result at ``patient_pose`` ``(4, 4)`` (camera poses ``X @ A_v``, ``rig``) against the mirrored CTA
    optimised from it; ``renderer`` renders the CTA as registered, ``views`` are the prepared runs."""
    from .tto import test_time_optimise, tto_views  # PyTorch, only when the test runs

    (monitor or Monitor()).step("mirror", 0.0, "weighing the result against the CTA mirrored left-right")
    mirrored = mirrored_volume(renderer.volume)
    start = view_poses(patient_pose, rig)
    result = test_time_optimise(TorchRenderer(mirrored, device), tto_views(views, start), TTOSchedule(MIRROR_TTO_ITERATIONS),
                                objective=objective, rig=rig)
    judge = make_renderer(mirrored, renderer.engine, device)
    return MirrorTest(pair_objective(renderer, start, views, objective), pair_objective(judge, result.poses, views, objective))
