"""Test-time optimisation with the GeoReg objective (paper section 2.3.3), in torch.

Per view: ``w * (-mNCC(target, DRR)) + (1 - w) * GeneralizedDice(sigmoid(cranium
channel), DSA mask > 0)``, summed over views (optionally plus the biplanar term).
Parameters per view: Euler ZYX (rad) and translation / 200 (mm); NAdam with a
OneCycle schedule. Coarse to fine: the first ``coarse_fraction`` of the steps
render at half the image size (a coarser CTA level, a quarter of the rays), the
rest at full size. Each view keeps the pose of best full-size mNCC seen, the start
included. Poses in and out are numpy ``(4, 4)`` (centred CTA frame, mm); this is
the one stage that needs PyTorch (gradients through the torch DRR kernel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .. import contract as C
from ..geometry.detector import Detector
from ..images import resize_bilinear
from ..render.renderer import TorchRenderer
from .progress import Monitor

__all__ = ["TTOView", "TTOSchedule", "TTOResult", "test_time_optimise", "biplanar_penalty"]

#: The render channels the objective uses: the total density and the cranium.
TTO_CHANNELS = ("total", "cranium")


@dataclass
class TTOView:
    """One view to optimise: target ``(h, w)`` (the preprocessed MAP at the acquisition SDD),
    the DSA cranium mask of the same shape, the acquisition detector sampled on ``h x w``,
    and the start pose ``(4, 4)``."""

    name: str
    target: np.ndarray
    mask: np.ndarray
    detector: Detector
    pose: np.ndarray


@dataclass(frozen=True)
class TTOSchedule:
    """Steps, peak learning rate (OneCycle, CONVENTIONS 5) and the share of steps at half size."""

    iterations: int = C.TTO_ITERATIONS
    max_lr: float = C.TTO_MAX_LR
    coarse_fraction: float = 0.4

    def coarse_steps(self) -> int:
        return int(round(self.iterations * self.coarse_fraction))


@dataclass
class TTOResult:
    """Best pose, its mNCC and iteration per view; ``trace``: per iteration the loss and per view
    the mNCC, Dice loss, image size and pose."""

    poses: dict[str, np.ndarray]
    best_mncc: dict[str, float]
    best_iteration: dict[str, int]
    trace: list[dict] = field(default_factory=list)


def biplanar_penalty(R_pa, R_lat):
    """``|angle(R_lat^T R_pa) - pi/2|`` (rad, torch): PA and lateral arms should be orthogonal."""
    from ..geometry.rigid import rotation_angle_rad

    return (rotation_angle_rad(R_lat.transpose(-1, -2) @ R_pa) - math.pi / 2).abs()


def _half(view: TTOView) -> tuple[np.ndarray, np.ndarray, Detector]:
    """The view's target, mask and detector at half the size (same field of view)."""
    det = view.detector.resized(max(16, view.detector.rows // 2), max(16, view.detector.cols // 2))
    target = resize_bilinear(view.target[None].astype(np.float32), det.shape)[0]
    mask = resize_bilinear((view.mask > 0).astype(np.float32)[None], det.shape)[0] > 0.5
    return target, mask, det


def test_time_optimise(
    renderer: TorchRenderer,
    views: list[TTOView],
    schedule: TTOSchedule = TTOSchedule(),
    *,
    biplanar: bool = False,
    monitor: Monitor | None = None,
) -> TTOResult:
    """Jointly optimise the poses of ``views`` through ``renderer``'s differentiable kernel."""
    import torch

    from ..geometry.rigid import params_from_pose, pose_from_params
    from ..metrics.losses import generalized_dice_loss, mncc_similarity

    monitor = monitor or Monitor()
    n = schedule.iterations
    if n < 0:
        raise ValueError(f"iterations must be >= 0, got {n}")
    dev = renderer.device
    channels = renderer.channel_index(TTO_CHANNELS)
    as_t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32), device=dev)[None, None]  # noqa: E731
    levels = {}
    for v in views:
        coarse_target, coarse_mask, coarse_det = _half(v)
        for size, (target, mask, det) in (("full", (v.target, v.mask, v.detector)), ("half", (coarse_target, coarse_mask, coarse_det))):
            drr = renderer.drr(renderer.level_for_pose(v.pose, det))
            levels[v.name, size] = (as_t(target), (as_t(mask) > 0).float(), det, drr)

    def objective(name: str, pose, size: str):
        target, mask, det, drr = levels[name, size]
        img = drr(pose, detector=det, channels=channels)
        sim = mncc_similarity(target, img[:, :1])
        dice = generalized_dice_loss(torch.sigmoid(img[:, 1:2]), mask)
        return C.TTO_NCC_WEIGHT * (-sim) + (1 - C.TTO_NCC_WEIGHT) * dice, sim, dice

    scale = C.TTO_TRANSLATION_SCALE_MM
    params = []
    for v in views:
        r, t = params_from_pose(torch.as_tensor(v.pose, dtype=torch.float64, device=dev)[None])
        params.append(torch.cat((r, t / scale), dim=-1).clone().requires_grad_(True))
    best = {v.name: (-math.inf, v.pose.copy(), 0) for v in views}
    coarse = schedule.coarse_steps() if n > 0 else 0
    if coarse > 0:  # the start, scored at full size (the coarse steps are not compared with it)
        with torch.no_grad():
            for v, p in zip(views, params):
                _, sim, _ = objective(v.name, pose_from_params(p[:, :3], p[:, 3:] * scale), "full")
                best[v.name] = (float(sim), v.pose.copy(), 0)
    result = TTOResult({}, {}, {})
    optimiser = scheduler = None
    if n > 0:
        optimiser = torch.optim.NAdam(params, lr=schedule.max_lr)
        scheduler = torch.optim.lr_scheduler.OneCycleLR(
            optimiser, max_lr=schedule.max_lr, total_steps=n, pct_start=C.TTO_WARMUP_FRACTION,
            div_factor=C.TTO_DIV_FACTOR, cycle_momentum=False,
        )
    for it in range(n + 1):
        final = it == n
        size = "half" if it < coarse else "full"
        monitor.step("tto", it / max(n, 1), f"iteration {it}/{n} ({size} size)")
        with torch.set_grad_enabled(not final):
            loss = torch.zeros((), dtype=torch.float64, device=dev)
            rotations = {}
            entry: dict = {"iteration": it, "size": size, "views": {}}
            for v, p in zip(views, params):
                pose = pose_from_params(p[:, :3], p[:, 3:] * scale)
                rotations[v.name] = pose[:, :3, :3]
                view_loss, sim, dice = objective(v.name, pose, size)
                loss = loss + view_loss
                score = float(sim.detach())
                pose_np = pose.detach()[0].cpu().numpy()
                entry["views"][v.name] = {"mncc": score, "dice_loss": float(dice.detach()), "pose": pose_np.tolist()}
                if size == "full" and score > best[v.name][0]:
                    best[v.name] = (score, pose_np, it)
            if biplanar and len(views) == 2:
                loss = loss + C.BIPLANAR_WEIGHT * biplanar_penalty(rotations[views[0].name], rotations[views[1].name]).sum()
            entry["loss"] = float(loss.detach())
            result.trace.append(entry)
            if not final:
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                scheduler.step()
    for name, (score, pose, it) in best.items():
        result.poses[name], result.best_mncc[name], result.best_iteration[name] = pose, score, it
    monitor.step("tto", 1.0, "done")
    return result
