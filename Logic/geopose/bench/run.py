"""Evaluate every operating point of the method on one benchmark case.

Rows (the paper's tables): the native acquisition pose, calibrated Init, Init + one
Refine update, Init + greedy Refine, each of those + ``iterations`` TTO steps, and
native + ``long_iterations`` TTO steps (0 skips it). The case is registered once by
:func:`geopose.register.register_case` (its Init, greedy and greedy + TTO poses are
rows); the other TTO rows run the same TTO stage from the other starts. Poses are
camera-to-centred-native ``(4, 4)`` (mm); metrics as ``geopose.metrics``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..geometry.poses import pose_from_carm_angles
from ..metrics.similarity import ncc
from ..nets.predictors import ModelSet
from ..options import RegistrationOptions
from ..register.case import VIEW_KEYS, silhouette_dice
from ..register.evaluate import carotid_mpcd, evaluate_pose
from ..register.pipeline import register_case, torch_renderer_for, tto_views
from ..register.results import CaseRegistration
from ..register.tto import TTOSchedule, test_time_optimise
from .cases import BenchCase

__all__ = ["BenchSettings", "row_names", "evaluate_case"]


@dataclass(frozen=True)
class BenchSettings:
    """How each case is run: the registration options plus the long native TTO budget."""

    options: RegistrationOptions = field(default_factory=RegistrationOptions)
    long_iterations: int = 400


def row_names(settings: BenchSettings, long: bool = True) -> list[str]:
    """Row labels in table order (the long-budget row only when ``long``)."""
    n = settings.options.iterations
    starts = ["native", "Init", "Init + Refine x1", "Init + greedy Refine"]
    rows = starts + [f"{s} + {n} TTO" for s in starts]
    if long and settings.long_iterations > 0:
        rows.append(f"native + {settings.long_iterations} TTO")
    return rows


def _metrics(reg: CaseRegistration, case: BenchCase, key: str, pose: np.ndarray) -> dict:
    """NCC and silhouette Dice in the TTO geometry, plus the truth metrics of ``evaluate_pose``
    (clDice only where the case has arteries)."""
    view = reg.views[key].prepared
    image = reg.renderer.render(pose, view.tto_detector, ("total", "cranium"))
    out = {"ncc": ncc(view.tto_image, image[0]), "silhouette_dice": silhouette_dice(image[1], view.tto_mask)}
    run = case.runs[key]
    return out | evaluate_pose(
        pose, case.true_poses[key], run.detector, run.angles.sod_mm, case.carotid_points_mm,
        renderer=reg.renderer if case.carotid_points_mm is not None else None, mask_detector=view.tto_detector,
    )


def _curves(case: BenchCase, trace: list[dict]) -> dict:
    """Per view the mNCC and mPCD (mm at the detector) of each pose in a TTO trace."""
    curves = {}
    for k in VIEW_KEYS:
        entries = [e["views"][k] for e in trace]
        mpcd = None
        if case.carotid_points_mm is not None:
            run = case.runs[k]
            poses = np.asarray([e["pose"] for e in entries])
            mpcd = [d.detector_mm for d in carotid_mpcd(poses, case.true_poses[k], run.detector, run.angles.sod_mm,
                                                        case.carotid_points_mm)]
        curves[k] = {"mncc": [e["mncc"] for e in entries], "mpcd_mm": mpcd}
    return curves


def evaluate_case(case: BenchCase, models: ModelSet, settings: BenchSettings, *, long: bool = True) -> dict:
    """All rows for ``case``: ``{"rows": {row: {view: metrics}}, "views": ..., "runtimes_s": ..., "curves": ...}``."""
    options = settings.options
    n = options.iterations
    reg = register_case(case.cta, case.runs, models=models, options=options, cranium_mask=case.cranium,
                        segmentation=case.vessels)
    times = {name: reg.runtimes_s[name] for name in ("prepare", "calibration", "init", "refine")}
    times["Init (both views)"] = times.pop("init")
    times["greedy Refine"] = times.pop("refine")
    times[f"{n} TTO from Init + greedy Refine"] = reg.runtimes_s["tto"]
    views = reg.views
    starts = {
        "native": {k: pose_from_carm_angles(case.runs[k].angles) for k in VIEW_KEYS},
        "Init": {k: views[k].init.pose_native for k in VIEW_KEYS},
        # one Refine update applied unconditionally: the first proposal of the greedy run
        "Init + Refine x1": {k: views[k].refine.proposals[0].pose if views[k].refine.proposals else views[k].refine.pose
                             for k in VIEW_KEYS},
        "Init + greedy Refine": {k: views[k].refine.pose for k in VIEW_KEYS},
    }
    poses: dict[str, dict[str, np.ndarray]] = dict(starts)
    curves: dict[str, dict] = {}
    budgets = [(name, n) for name in ("native", "Init", "Init + Refine x1")]
    if long and settings.long_iterations > 0:
        budgets.append(("native", settings.long_iterations))
    if reg.tto is not None:
        poses[f"Init + greedy Refine + {n} TTO"] = {k: views[k].final_pose for k in VIEW_KEYS}
        curves[f"Init + greedy Refine + {n} TTO"] = _curves(case, reg.tto.trace)
        tto_renderer = torch_renderer_for(reg.renderer)
        for name, budget in budgets:
            t0 = time.perf_counter()
            result = test_time_optimise(tto_renderer, tto_views({k: views[k].prepared for k in VIEW_KEYS}, starts[name]), TTOSchedule(budget),
                                        biplanar=options.biplanar)
            times[f"{budget} TTO from {name}"] = time.perf_counter() - t0
            poses[f"{name} + {budget} TTO"] = dict(result.poses)
            curves[f"{name} + {budget} TTO"] = _curves(case, result.trace)
    rows = {row: {k: _metrics(reg, case, k, p[k]) for k in VIEW_KEYS} for row, p in poses.items()}
    view_info = {k: {"true_view": case.runs[k].view_label, "init_view": views[k].init.view,
                     "greedy_accepted": views[k].refine.accepted} for k in VIEW_KEYS}
    return {"case": case.name, "notes": case.notes + reg.notes, "rows": rows, "views": view_info, "runtimes_s": times,
            "curves": curves, "device": reg.engine["device"], "engine": reg.engine}
