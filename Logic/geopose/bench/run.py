"""Evaluate every operating point of the method on one benchmark case.

Rows:

* ``DICOM angles``: the acquisition's own geometry (the native start), and ``DICOM angles +
  n TTO`` from it with the default TTO (one patient pose; a run of its own, as the drift row's):
  what the networks add;
* ``biplane: Init``, ``biplane: greedy Refine``, ``biplane: greedy Refine + n TTO``: the
  default registration (one patient pose seen by both arms; :func:`register_case`);
* ``independent: Init``, ``... + Refine x1``, ``... greedy Refine``, ``... greedy Refine + n
  TTO``: the published pipeline (each view on its own, the paper's objective and schedule);
* ``truth + n TTO``: the default TTO started at the true pose: how far the objective's
  optimum lies from the truth (drift);
* ``upper bound (truth masks): ...``: the default registration handed the case's true cranium and
  vessel masks, which a user does not have: how much better the registration would be with a
  perfect CTA segmentation (the gap to the default rows is a reported number).

Every other row runs the user's path: the CTA and the two runs only, the masks computed by
:func:`register_case` as for ``geopose register`` without ``--segmentation`` or ``--cranium-mask``.
The case's true masks serve only for scoring (clDice, silhouette Dice) and the upper-bound rows.
* ``DICOM angles + long TTO`` (``long_iterations``; 0 skips it).

Poses are camera-to-centred-native ``(4, 4)`` (mm); metrics as ``geopose.metrics``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..metrics.similarity import ncc
from ..nets.predictors import ModelSet
from ..options import RegistrationOptions
from ..register.biplane import nominal_poses, patient_pose
from ..register.case import VIEW_KEYS, silhouette_dice
from ..register.evaluate import carotid_mpcd, evaluate_pose
from ..register.engine import torch_renderer_for
from ..register.pipeline import register_case
from ..register.results import CaseRegistration
from ..register.tto import TTOSchedule, test_time_optimise, tto_views
from ..render.renderer import Renderer
from .cases import BenchCase, flipped_left_right

__all__ = ["BenchSettings", "row_names", "evaluate_case", "evaluate_mirrored", "evaluate_crossed", "MIRRORED_SUFFIX",
           "crossed_name", "LEARNED_ROW",
           "NATIVE_TTO_ROW", "DRIFT_ROW", "INSTANT_ROW",
           "SEARCH_ROW", "UPPER_BOUND_ROW", "UPPER_BOUND_SEARCH_ROW"]

#: The default registration's rows (the targets refer to them).
INSTANT_ROW = "biplane: greedy Refine"
#: The default registration's pose before the TTO: greedy Refine and the similarity search.
SEARCH_ROW = "biplane: greedy Refine + search"
LEARNED_ROW = "biplane: greedy Refine + {n} TTO"
NATIVE_TTO_ROW = "DICOM angles + {n} TTO"
DRIFT_ROW = "truth + {n} TTO (drift)"
#: The default registration given the case's true masks (not the user's path: an upper bound).
UPPER_BOUND_ROW = "upper bound (truth masks): greedy Refine + {n} TTO"
UPPER_BOUND_SEARCH_ROW = "upper bound (truth masks): greedy Refine + search"
#: Case-name suffix of a case registered with its CTA mirrored left-right (:func:`evaluate_mirrored`).
MIRRORED_SUFFIX = "-mirrored"


@dataclass(frozen=True)
class BenchSettings:
    """How each case is run: the registration options plus the long native TTO budget."""

    options: RegistrationOptions = field(default_factory=RegistrationOptions)
    long_iterations: int = 400


def row_names(settings: BenchSettings, long: bool = True) -> list[str]:
    """Row labels in table order (the long-budget row only when ``long``)."""
    n = settings.options.tto.iterations
    rows = [
        "DICOM angles", NATIVE_TTO_ROW.format(n=n),
        "biplane: Init", INSTANT_ROW, *([SEARCH_ROW] if settings.options.search.enabled else []), LEARNED_ROW.format(n=n),
        "independent: Init", "independent: Init + Refine x1", "independent: greedy Refine",
        f"independent: greedy Refine + {n} TTO",
        DRIFT_ROW.format(n=n),
        *([UPPER_BOUND_SEARCH_ROW] if settings.options.search.enabled else []), UPPER_BOUND_ROW.format(n=n),
    ]
    if long and settings.long_iterations > 0:
        rows.append(f"DICOM angles + {settings.long_iterations} TTO")
    return rows


def _metrics(reg: CaseRegistration, scorer: Renderer, case: BenchCase, key: str, pose: np.ndarray) -> dict:
    """NCC (against the run's TTO target) and the true cranium's silhouette Dice in the TTO geometry,
    plus the truth metrics of ``evaluate_pose`` (clDice of the TRUE vessels, only where the case has
    arteries); ``scorer`` renders the CTA with the case's true masks."""
    view = reg.views[key].prepared
    image = scorer.render(pose, view.tto_detector, ("total", "cranium"))
    out = {"ncc": ncc(view.tto_image, image[0]), "silhouette_dice": silhouette_dice(image[1], view.tto_mask)}
    run = case.runs[key]
    return out | evaluate_pose(
        pose, case.true_poses[key], run.detector, run.angles.sod_mm, case.carotid_points_mm,
        renderer=scorer if case.carotid_points_mm is not None else None, mask_detector=view.tto_detector,
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
    options = settings.options.replace(independent_views=False)
    n = options.tto.iterations
    joint = register_case(case.cta, case.runs, models=models, options=options)
    paper = register_case(case.cta, case.runs, models=models, options=options.replace(independent_views=True))
    upper = register_case(case.cta, case.runs, models=models, options=options, cranium_mask=case.cranium,
                          segmentation=case.vessels)
    scorer = upper.renderer
    stages = ("prepare", "calibration", "init", "refine", "search", "tto", "mirror", "pairing", "total")
    times = {f"{stage} (biplane)": joint.runtimes_s[stage] for stage in stages if stage in joint.runtimes_s}
    times |= {f"{stage} (independent)": paper.runtimes_s[stage] for stage in ("refine", "tto", "total")}
    rig = nominal_poses(case.runs)
    poses: dict[str, dict[str, np.ndarray]] = {
        "DICOM angles": dict(rig),
        "biplane: Init": {k: joint.views[k].init_pose for k in VIEW_KEYS},
        INSTANT_ROW: {k: joint.views[k].refine.pose for k in VIEW_KEYS},
        **({SEARCH_ROW: {k: joint.views[k].search_pose for k in VIEW_KEYS}} if joint.registration.search else {}),
        "independent: Init": {k: paper.views[k].init_pose for k in VIEW_KEYS},
        # one Refine update applied unconditionally: the first proposal of the greedy run
        "independent: Init + Refine x1": {k: (paper.views[k].refine.proposals or [paper.views[k].refine])[0].pose
                                          for k in VIEW_KEYS},
        "independent: greedy Refine": {k: paper.views[k].refine.pose for k in VIEW_KEYS},
        **({UPPER_BOUND_SEARCH_ROW: {k: upper.views[k].search_pose for k in VIEW_KEYS}} if upper.registration.search else {}),
    }
    curves: dict[str, dict] = {}
    if joint.tto is not None:
        poses[LEARNED_ROW.format(n=n)] = {k: joint.views[k].final_pose for k in VIEW_KEYS}
        poses[f"independent: greedy Refine + {n} TTO"] = {k: paper.views[k].final_pose for k in VIEW_KEYS}
        poses[UPPER_BOUND_ROW.format(n=n)] = {k: upper.views[k].final_pose for k in VIEW_KEYS}
        curves[LEARNED_ROW.format(n=n)] = _curves(case, joint.tto.trace)
        tto_renderer = torch_renderer_for(joint.renderer)
        views = {k: joint.views[k].prepared for k in VIEW_KEYS}
        # The native row is a TTO run of its own from the DICOM angles: the registration's run from there stops
        # after the coarse steps when it falls behind (TTOSchedule.stop_behind).
        budgets = [(NATIVE_TTO_ROW.format(n=n), rig, n), (DRIFT_ROW.format(n=n), case.true_poses, n)]
        if long and settings.long_iterations > 0:
            budgets.append((f"DICOM angles + {settings.long_iterations} TTO", rig, settings.long_iterations))
        for name, start, budget in budgets:
            X = patient_pose(start["pa"], rig["pa"])
            t0 = time.perf_counter()
            result = test_time_optimise(tto_renderer, tto_views(views, {k: X @ rig[k] for k in VIEW_KEYS}),
                                        TTOSchedule(budget), rig=rig)
            times[f"{name}"] = time.perf_counter() - t0
            poses[name] = dict(result.poses)
            curves[name] = _curves(case, result.trace)
    rows = {row: {k: _metrics(joint, scorer, case, k, p[k]) for k in VIEW_KEYS} for row, p in poses.items()}
    view_info = {k: {"true_view": case.runs[k].view_label, "init_view": paper.views[k].init.view,
                     "greedy_accepted": joint.views[k].refine.accepted} for k in VIEW_KEYS}
    registration = joint.registration
    return {"case": case.name, "notes": case.notes + joint.notes, "rows": rows, "views": view_info, "runtimes_s": times,
            "curves": curves, "device": joint.engine["device"], "engine": joint.engine,
            "start": {"chosen": registration.chosen_start, "objective": registration.starts,
                      "refine": registration.refine_start,
                      "tto_objective": registration.tto_objective},
            "checks": registration.checks,
            "masks": joint.labels_source} | _verdicts(joint)


def _verdicts(reg: CaseRegistration) -> dict:
    """What a registration says of itself: the flags and their reasons per view, the mirror and pairing tests."""
    registration = reg.registration
    return {"quality": {k: reg.views[k].quality.flag for k in VIEW_KEYS},
            "quality_reasons": {k: list(reg.views[k].quality.reasons) for k in VIEW_KEYS},
            "mirror": None if registration.mirror is None else registration.mirror.as_dict(),
            "pairing": None if registration.pairing is None else registration.pairing.as_dict()}


def _tests(reg: CaseRegistration, name: str) -> dict:
    """What a case registered outside the benchmark's rows reports: its name, notes, time, device and verdicts."""
    return {"case": name, "notes": reg.notes, "runtimes_s": {"total": reg.runtimes_s["total"]},
            "device": reg.engine["device"]} | _verdicts(reg)


def evaluate_mirrored(case: BenchCase, models: ModelSet, settings: BenchSettings) -> dict:
    """The default registration of ``case`` with its CTA's array flipped left-right, the header kept (a CTA whose
    header swaps the patient's sides): the user's path (the CTA and the two runs, masks computed). It must come out
    failed; the mirror test's numbers (``register/mirror.py``), the flags and the reasons, per view."""
    reg = register_case(flipped_left_right(case.cta), case.runs, models=models,
                        options=settings.options.replace(independent_views=False))
    return _tests(reg, case.name + MIRRORED_SUFFIX)


def crossed_name(cta_case: str, runs_case: str) -> str:
    """The name of a wrong pairing: the CTA of the case named ``cta_case`` with the runs of ``runs_case``."""
    return f"{cta_case}-cta+{runs_case}-runs"


def evaluate_crossed(cta_case: BenchCase, runs_case: BenchCase, models: ModelSet, settings: BenchSettings) -> dict:
    """A wrong pairing: the default registration of ``cta_case``'s CTA with ``runs_case``'s two runs, as a user who
    picked another patient's CTA (anonymised, or a NIfTI CTA without identifiers) would run it, masks computed. It must
    come out failed; the mirror and pairing tests' numbers, the flags and the reasons, per view."""
    reg = register_case(cta_case.cta, runs_case.runs, models=models, options=settings.options.replace(independent_views=False))
    return _tests(reg, crossed_name(cta_case.name, runs_case.name))
