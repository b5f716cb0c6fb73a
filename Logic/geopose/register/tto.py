"""Test-time optimisation with the GeoReg objective (paper section 2.3.3).

Per view: ``w * (-mNCC(target, DRR)) + (1 - w) * GeneralizedDice(sigmoid(cranium
channel), DSA mask > 0)``, summed over views (optionally plus the biplanar
term). Parameters per view: Euler ZYX (rad) and translation / 200 (mm); NAdam
with a OneCycle schedule; each view keeps the pose of best mNCC seen,
iteration 0 included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from .. import contract as C
from ..geometry import Detector, params_from_pose, pose_from_params, rotation_angle_rad
from ..metrics import generalized_dice_loss, mncc
from ..render import DRR
from .progress import Monitor

__all__ = ["TTOView", "TTOResult", "test_time_optimise", "biplanar_penalty"]


@dataclass
class TTOView:
    """One view to optimise: target ``(1, 1, h, w)``, DSA cranium mask of the same
    shape, the acquisition detector sampled on ``h x w``, and the start pose."""

    name: str
    target: Tensor
    mask: Tensor
    detector: Detector
    pose: Tensor


@dataclass
class TTOResult:
    poses: dict[str, Tensor]
    best_mncc: dict[str, float]
    best_iteration: dict[str, int]
    trace: list[dict] = field(default_factory=list)


def biplanar_penalty(R_pa: Tensor, R_lat: Tensor) -> Tensor:
    """``|angle(R_lat^T R_pa) - pi/2|`` (rad): PA and lateral arms should be orthogonal."""
    return (rotation_angle_rad(R_lat.transpose(-1, -2) @ R_pa) - math.pi / 2).abs()


def test_time_optimise(
    drr: DRR,
    views: list[TTOView],
    iterations: int = C.TTO_ITERATIONS,
    max_lr: float = C.TTO_MAX_LR,
    cranium_channel: int = 1,
    biplanar: bool = False,
    monitor: Monitor | None = None,
) -> TTOResult:
    """Jointly optimise the poses of ``views`` through the differentiable renderer."""
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    monitor = monitor or Monitor()
    scale = C.TTO_TRANSLATION_SCALE_MM
    params = []
    for v in views:
        r, t = params_from_pose(v.pose.detach().double())
        params.append(torch.cat((r, t / scale), dim=-1).float().clone().requires_grad_(True))
    best_score = {v.name: -math.inf for v in views}
    best_pose = {v.name: v.pose.detach().clone() for v in views}
    best_iter = {v.name: 0 for v in views}
    result = TTOResult(best_pose, best_score, best_iter)
    optimiser = scheduler = None
    if iterations > 0:
        optimiser = torch.optim.NAdam(params, lr=max_lr)
        scheduler = torch.optim.lr_scheduler.OneCycleLR(
            optimiser, max_lr=max_lr, total_steps=iterations, pct_start=C.TTO_WARMUP_FRACTION,
            div_factor=C.TTO_DIV_FACTOR, cycle_momentum=False,
        )
    for it in range(iterations + 1):
        final = it == iterations
        monitor.step("tto", it / max(iterations, 1), f"iteration {it}/{iterations}")
        with torch.set_grad_enabled(not final):
            loss = torch.zeros((), device=drr.density.device)
            rotations = {}
            entry: dict = {"iteration": it, "views": {}}
            for v, p in zip(views, params):
                pose = pose_from_params(p[:, :3], p[:, 3:] * scale)
                rotations[v.name] = pose[:, :3, :3]
                img = drr(pose, detector=v.detector, channels=(0, cranium_channel))
                sim = mncc(v.target, img[:, :1])
                dice = generalized_dice_loss(torch.sigmoid(img[:, 1:2]), (v.mask > 0).float())
                loss = loss + C.TTO_NCC_WEIGHT * (-sim) + (1 - C.TTO_NCC_WEIGHT) * dice
                score = float(sim.detach())
                entry["views"][v.name] = {"mncc": score, "dice_loss": float(dice.detach()), "pose": pose.detach()[0].tolist()}
                if score > best_score[v.name]:
                    best_score[v.name], best_pose[v.name], best_iter[v.name] = score, pose.detach().clone(), it
            if biplanar and len(views) == 2:
                names = [v.name for v in views]
                loss = loss + C.BIPLANAR_WEIGHT * biplanar_penalty(rotations[names[0]], rotations[names[1]]).sum()
            entry["loss"] = float(loss.detach())
            result.trace.append(entry)
            if not final:
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                scheduler.step()
    monitor.step("tto", 1.0, "done")
    return result
