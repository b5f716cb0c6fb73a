"""Evaluate every operating point of the method on one benchmark case.

Rows (the paper's tables): the native acquisition pose, calibrated Init, Init +
one Refine update, Init + greedy Refine, each of those + ``iterations`` TTO
steps, and native + ``long_iterations`` TTO steps (0 skips it). Poses are
camera-to-centred-native ``(1, 4, 4)`` (mm); metrics as ``geopose.metrics``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from .. import contract as C
from ..geometry import pose_from_carm_angles
from ..metrics import ncc
from ..nets import InitPredictor, RefinePredictor
from ..register import (
    RegistrationOptions, calibrate, calibrated_init, greedy_refine, prepare_case, test_time_optimise,
)
from ..register.case import CRANIUM_CHANNEL, VESSEL_CHANNEL, VIEW_KEYS
from ..register.evaluate import carotid_mpcd, evaluate_pose
from ..register.pipeline import PreparedCase, silhouette_dice, synchronize
from .cases import BenchCase

__all__ = ["BenchSettings", "row_names", "evaluate_case"]


@dataclass
class BenchSettings:
    """How each case is run: TTO budgets, refinement proposals and device."""

    iterations: int = C.TTO_ITERATIONS
    long_iterations: int = 400
    refine_steps: int = C.GREEDY_MAX_PROPOSALS
    device: str = "auto"
    tto_px: int | None = None
    model_clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES


def row_names(settings: BenchSettings, long: bool = True) -> list[str]:
    """Row labels in table order (the long-budget row only when ``long``)."""
    n = settings.iterations
    starts = ["native", "Init", "Init + Refine x1", "Init + greedy Refine"]
    rows = starts + [f"{s} + {n} TTO" for s in starts]
    if long and settings.long_iterations > 0:
        rows.append(f"native + {settings.long_iterations} TTO")
    return rows


def _metrics(prep: PreparedCase, case: BenchCase, key: str, pose: torch.Tensor) -> dict:
    """NCC and silhouette Dice in the TTO geometry, plus the truth metrics of ``evaluate_pose``
    (mPCD and clDice only where the case has arteries)."""
    view = prep.views[key]
    pose = pose.to(prep.device, torch.float32)
    with torch.no_grad():
        img = prep.drr(pose, detector=view.tto_detector, channels=(0,))
    out = {"ncc": float(ncc(prep.tto_target(key), img)), "silhouette_dice": silhouette_dice(prep.drr, pose, view)}
    run = case.runs[key]
    arteries = case.carotid_points_mm is not None
    return out | evaluate_pose(
        pose, torch.as_tensor(case.true_poses[key]), run.detector, run.angles.sod_mm, case.carotid_points_mm,
        drr=prep.drr if arteries else None, vessel_channel=VESSEL_CHANNEL, mask_detector=view.tto_detector,
    )


def _curve_mpcd(case: BenchCase, key: str, poses: list) -> list[float] | None:
    """mPCD (mm at the detector) of each pose in a TTO trace."""
    if case.carotid_points_mm is None:
        return None
    run = case.runs[key]
    est = torch.as_tensor(np.asarray(poses), dtype=torch.float64)
    return [d.detector_mm for d in carotid_mpcd(est, torch.as_tensor(case.true_poses[key]), run.detector, run.angles.sod_mm, case.carotid_points_mm)]


def _tto(prep: PreparedCase, case: BenchCase, starts: dict[str, torch.Tensor], iterations: int) -> tuple[dict, dict, float]:
    """Joint TTO of both views from ``starts``: final poses, per-view curves, seconds."""
    t0 = time.perf_counter()
    result = test_time_optimise(
        prep.drr, [prep.tto_view(k, starts[k]) for k in VIEW_KEYS], iterations, cranium_channel=CRANIUM_CHANNEL
    )
    synchronize(prep.device)
    seconds = time.perf_counter() - t0
    curves = {}
    for k in VIEW_KEYS:
        entries = [e["views"][k] for e in result.trace]
        curves[k] = {"mncc": [e["mncc"] for e in entries], "mpcd_mm": _curve_mpcd(case, k, [e["pose"] for e in entries])}
    return dict(result.poses), curves, seconds


def evaluate_case(
    case: BenchCase, init: InitPredictor, refine: RefinePredictor, settings: BenchSettings, *, long: bool = True
) -> dict:
    """All rows for ``case``: ``{"rows": {row: {view: metrics}}, "views": ..., "runtimes_s": ..., "curves": ...}``."""
    options = RegistrationOptions(refine_steps=settings.refine_steps, device=settings.device, tto_px=settings.tto_px,
                                  model_clip_percentiles=settings.model_clip_percentiles)
    t0 = time.perf_counter()
    prep = prepare_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels, options=options)
    times = {"prepare": time.perf_counter() - t0}

    t0 = time.perf_counter()
    cal = calibrate(prep.drr, init)
    synchronize(prep.device)
    times["calibration"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    inits = {k: calibrated_init(prep.model_target(k), k == "lat", init, cal) for k in VIEW_KEYS}
    synchronize(prep.device)
    times["Init (both views)"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    single = {k: greedy_refine(prep.drr, prep.model_target(k), inits[k].pose_native.float(), inits[k].view, refine, 1) for k in VIEW_KEYS}
    synchronize(prep.device)
    times["Refine x1"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    greedy = {
        k: greedy_refine(prep.drr, prep.model_target(k), inits[k].pose_native.float(), inits[k].view, refine, settings.refine_steps)
        for k in VIEW_KEYS
    }
    synchronize(prep.device)
    times["greedy Refine"] = time.perf_counter() - t0

    dev = prep.device
    starts = {
        "native": {k: pose_from_carm_angles(case.runs[k].angles).matrix.float().to(dev) for k in VIEW_KEYS},
        "Init": {k: inits[k].pose_native.float() for k in VIEW_KEYS},
        # one Refine update applied unconditionally: the first proposal of a greedy run
        "Init + Refine x1": {k: single[k].proposals[0].pose.float() for k in VIEW_KEYS},
        "Init + greedy Refine": {k: greedy[k].pose.float() for k in VIEW_KEYS},
    }
    poses: dict[str, dict[str, torch.Tensor]] = dict(starts)
    curves = {}
    n = settings.iterations
    for name, start in starts.items():
        final, curves[f"{name} + {n} TTO"], seconds = _tto(prep, case, start, n)
        poses[f"{name} + {n} TTO"] = final
        times[f"{n} TTO from {name}"] = seconds
    if long and settings.long_iterations > 0:
        name = f"native + {settings.long_iterations} TTO"
        poses[name], curves[name], times[f"{settings.long_iterations} TTO from native"] = _tto(
            prep, case, starts["native"], settings.long_iterations
        )
    rows = {row: {k: _metrics(prep, case, k, p[k]) for k in VIEW_KEYS} for row, p in poses.items()}
    views = {k: {"true_view": case.runs[k].view_label, "init_view": inits[k].view, "greedy_accepted": greedy[k].accepted} for k in VIEW_KEYS}
    return {"case": case.name, "notes": case.notes, "rows": rows, "views": views, "runtimes_s": times, "curves": curves,
            "device": str(dev)}
