"""The GeoPose registration of one case, stage by stage: ``register_case``.

Read top to bottom, :func:`register_case` is the whole method (paper section 2.3):

1. ``prepare_case``: CTA masks and render volume, each DSA run's MAP, cranium mask and
   preprocessed images (``case.py``);
2. ``calibrate``: one DRR of the native CTA at the PA isopose and one Init pass give the
   canonical -> native frame transfer (``calibration.py``);
3. ``calibrated_init``: Init on each view's MAP, moved into the native frame;
4. ``greedy_refine``: Refine proposals accepted while the mNCC improves (``refine.py``);
   one patient pose seen by both arms then gets a ``similarity_search`` of its shift and
   in-plane turns by the same score (``search.py``; ours);
5. ``test_time_optimise``: the GeoReg objective through the differentiable renderer
   (``tto.py``; needs PyTorch, skipped with a note without it);
6. ``score``: final mNCC, silhouette Dice and the quality flag per view (``quality.py``).

By default the two runs are one biplane acquisition: one patient pose ``X`` places both
C-arms (``T_v = X @ A_v``, ``A_v`` from each run's DICOM geometry; ``biplane.py``). Init's
per-view estimates are fused into ``X`` by what each view observes, Refine's proposals
likewise, the similarity search moves ``X`` while the views' mNCC improves, and the TTO
optimises ``X`` against both views from every distinct candidate start (the DICOM-angle
pose, the fused Init, each view's Init alone, Refine + search) through its coarse steps,
then from the DICOM angles and the best other start (by the objective, ``objective.py``) to
the end; the lower final objective wins (the DICOM angles' within a tie), so the result is
never worse, by the objective, than the acquisition's own geometry. A CTA without vessels (no
contrast, or a segmentation that found none) leaves the head's silhouette as the only evidence:
the result then starts from the DICOM angles alone and its move from there is bounded
(``bound.py``); the quality flag says so. A vessel mask computed from the CTA (no segmentation
given) is an approximation whose objective can lie degrees from the truth: a TTO result that moved
the networks' estimate further than the stages may disagree is not kept; nor is a TTO result whose objective
stays above ``WEAK_OBJECTIVE`` (runs that hold too little image evidence to tell poses apart). With vessels and
the TTO, the result is then weighed
against the CTA mirrored left-right (``mirror.py``): a header that swaps the patient's sides fits
the silhouette but not the vessels.
``independent_views=True`` runs the published pipeline: each view on its own, the paper's
objective and schedule.

Both engines run the same stages: ``backend="torch"`` renders with the torch kernel and
runs the torch networks, ``"onnxruntime"`` renders with the numpy kernel and runs the
shipped ONNX graphs; only the kernel and the network runtime differ. Poses between
stages are float64 numpy ``(4, 4)`` camera-to-world in the centred native CTA frame (mm).
The CLI, the demo, the benchmark and the Slicer module all call these functions.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import replace
from typing import Iterator, Mapping

import numpy as np

from .. import contract as C
from ..dsa import DSARun, PreparedDSA
from ..errors import InputError
from ..metrics.measures import pose_error_components
from ..metrics.similarity import mncc
from ..nets.predictors import ModelSet, load_models, resolve_torch_device
from ..options import RegistrationOptions
from ..render.renderer import Renderer, TorchRenderer, make_renderer
from ..volume import Volume
from .biplane import axis_disagreement_mm, combined_starts, fuse_patient_poses, nominal_poses, patient_pose, view_poses
from .bound import bound_move
from .calibration import calibrate, calibrated_init
from .case import TTO_PX_CPU, TTO_PX_CUDA, VIEW_KEYS, PreparedCase, prepare_case, silhouette_dice
from .evidence import view_evidence
from .mirror import mirror_test
from .objective import PAPER_OBJECTIVE, pair_objective
from .progress import CancelCheck, Monitor, ProgressCallback
from .quality import AGREEMENT_DEG, AGREEMENT_MM, VIEW_DISAGREEMENT_MM, Quality, assess
from .refine import greedy_refine, refine_from_starts
from .results import CaseRegistration, InitEstimate, Registration, ViewOutcome
from .search import similarity_search
from .tto import PAPER_SCHEDULE, TTOResult, TTOSchedule, test_time_optimise, test_time_optimise_starts, tto_views

__all__ = [
    "DICOM_START", "SEARCHED_START", "Engine", "NO_TORCH_TTO_NOTE", "NO_VESSELS_NOTE", "OBJECTIVE_TIE", "chosen_result",
    "resolve_engine",
    "register_case", "score_view", "torch_available", "torch_renderer_for", "tto_views",
]

#: The candidate start at the DICOM angles' geometry (``X = I``).
DICOM_START = "DICOM angles"
#: The candidate start after greedy Refine and the similarity search.
SEARCHED_START = "Refine + search"

#: Said (progress, record, Slicer table) when the test-time optimisation cannot run.
NO_TORCH_TTO_NOTE = ("PyTorch is not installed: calibration, Init and Refine ran on onnxruntime; the test-time "
                     "optimisation needs PyTorch and was skipped")

#: Said (record, flag) when the CTA's vessel mask is empty: the silhouette is the only evidence.
NO_VESSELS_NOTE = ("the CTA shows no contrast-filled vessels (none found, or none given): the pose rests on the head's "
                   "silhouette alone, so it started from the DICOM angles and its move from there was bounded")

#: Said (record, flag) when the TTO on a vessel mask computed from the CTA moved the networks' estimate further
#: than the stages may disagree (quality.AGREEMENT_DEG / AGREEMENT_MM): that estimate is kept.
APPROXIMATE_VESSELS_NOTE = ("the test-time optimisation, scored on the vessel mask computed from the CTA (an approximation: "
                            "give a vessel segmentation for the full accuracy), moved the networks' estimate by {rot:.1f} deg / "
                            "{mm:.0f} mm; the networks' estimate (greedy Refine + search) was kept")

#: Objective (summed over both views; lower is better) above which the runs hold too little image evidence
#: to choose between starts: the networks' estimate is kept. Set between the weakest validation result with
#: vessels (phantoms 6010-6029 and real heads, default path: -0.35) and the 128-px phantom cases whose TTO
#: ended 40-70 mm off a networks' estimate of 0.8-2.3 mm (seed 0: the shipped Resources/Testing case -0.14 and
#: -0.005, the same seed in today's world -0.27). On the 42-phantom benchmark it changes no result (weakest
#: -0.28, a case whose TTO had already been refused).
WEAK_OBJECTIVE = -0.3

#: Said (record, flag) when the TTO's best objective is above WEAK_OBJECTIVE.
WEAK_EVIDENCE_NOTE = ("the runs hold little image evidence (best objective {objective:.3f} > {limit:g}, both views summed): "
                      "the test-time optimisation cannot tell poses apart, so the networks' estimate (greedy Refine + "
                      "search) was kept")

#: Objective difference (summed over both views) within which two TTO results tie; on a tie the
#: DICOM angles' result is kept. Finalists' objectives on the 40 benchmark phantoms differ by at
#: least 1.5e-3; a learned start that wins by 1e-5 is noise, and the acquisition's own geometry
#: is the safer of two equal answers (docs/benchmark/bench.md, reading).
OBJECTIVE_TIE = 1e-3


def chosen_result(objectives: Mapping[str, float]) -> str:
    """The start whose TTO result is kept: the lowest final objective, the DICOM angles' on a tie
    (:data:`OBJECTIVE_TIE`)."""
    return min(objectives, key=lambda k: objectives[k] - (OBJECTIVE_TIE if k == DICOM_START else 0.0))


def torch_available() -> bool:
    """Whether PyTorch imports here (a broken install counts as missing)."""
    try:
        import torch  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


class Engine:
    """What a registration runs on: the renderer, the networks, and (when PyTorch is there) the
    differentiable renderer of the test-time optimisation. Build with :func:`resolve_engine`."""

    def __init__(self, renderer: Renderer, models: ModelSet, tto_renderer: TorchRenderer | None) -> None:
        self.renderer = renderer
        self.models = models
        self.tto_renderer = tto_renderer

    @property
    def device(self) -> str:
        return str(getattr(self.renderer, "device", "cpu"))

    def synchronize(self) -> None:
        """Wait for queued CUDA work, so a timing boundary measures it (no-op on the CPU)."""
        if self.device.startswith("cuda"):
            import torch

            torch.cuda.synchronize(self.device)

    def describe(self, options: RegistrationOptions, case: PreparedCase) -> dict:
        """The engine as the result record states it."""
        return {
            "backend": self.models.runtime,
            "renderer": self.renderer.engine,
            "device": self.device,
            "tto": "torch" if self.tto_renderer is not None else "skipped (PyTorch not installed)",
            "render_px": options.render_px or self.models.render_px,
            "tto_px": case.views["pa"].tto_detector.shape,
            "model_clip_percentiles": list(options.model_clip_percentiles or self.models.clip_percentiles),
            "models": self.models.files,
            "cta_levels_mm": {"x".join(map(str, f)): [round(s, 3) for s in lvl.spacing_mm]
                              for f, lvl in case.volume.levels.items()},
        }


def resolve_engine(
    options: RegistrationOptions, models: str | ModelSet | None = None, *, allow_unverified: bool = False
) -> tuple[str, str, ModelSet]:
    """``(backend, device, models)`` for ``options``: ``auto`` takes torch when it is installed,
    CUDA when present; the networks come from ``models`` (a folder, default the shipped models,
    or an already loaded :class:`ModelSet`, which must match the backend; ``allow_unverified``:
    a folder without a manifest)."""
    has_torch = torch_available()
    backend = options.backend if options.backend != "auto" else ("torch" if has_torch else "onnxruntime")
    if backend == "torch" and not has_torch:
        raise InputError("backend 'torch' was asked for but PyTorch is not installed: install PyTorch, or use "
                         "backend 'onnxruntime' (Init + Refine without the test-time optimisation)")
    if backend == "torch":
        device = str(resolve_torch_device(options.device))
    else:
        device = "cuda" if options.device.startswith("cuda") else "cpu"
    if isinstance(models, ModelSet):
        if models.runtime != backend:
            raise InputError(f"the loaded models run on {models.runtime} but backend {backend!r} was asked for; "
                             "load them with the same runtime")
        return backend, device, models
    return backend, device, load_models(models, runtime=backend, device=device, allow_unverified=allow_unverified)


@contextmanager
def _timed(times: dict[str, float], name: str, engine: Engine) -> Iterator[None]:
    t0 = time.perf_counter()
    yield
    engine.synchronize()
    times[name] = time.perf_counter() - t0


def torch_renderer_for(renderer: Renderer) -> TorchRenderer | None:
    """The differentiable renderer of ``renderer``'s volume (itself when it is one; on the CPU,
    sharing the volume's arrays, when it is the numpy one); None without PyTorch."""
    if isinstance(renderer, TorchRenderer):
        return renderer
    return TorchRenderer(renderer.volume, "cpu") if torch_available() else None


def score_view(renderer: Renderer, pose: np.ndarray, prepared: PreparedDSA) -> tuple[float, float]:
    """(mNCC of the DRR at ``pose`` against the TTO target, hard Dice of the projected cranium
    and the DSA cranium mask), both in the TTO geometry (acquisition SDD)."""
    image = renderer.render(pose, prepared.tto_detector, ("total", "cranium"))
    return mncc(prepared.tto_image, image[0]), silhouette_dice(image[1], prepared.tto_mask)


def _consistency_doubts(key: str, init: InitEstimate, label: int, registration: Registration) -> tuple[str, ...]:
    """The failed consistency checks of one view, worded for its quality flag."""
    doubts = []
    if init.network_view != label:
        doubts.append(f"the network reads this view as {C.VIEW_NAMES[init.network_view]} but its acquisition angle says "
                      f"{C.VIEW_NAMES[label]}: check the runs' angles (docs/conventions.md section 7)")
    if not registration.vessel_evidence:
        bound = registration.bound
        doubts.append("no vessel evidence: the CTA shows no contrast-filled vessels, so the pose rests on the head's "
                      "silhouette alone" + ("" if bound is None or not bound.bounded else
                                            f"; its move from the DICOM angles was bounded ({bound.rotation_deg:.1f} deg / "
                                            f"{bound.shift_mm:.0f} mm asked, {100 * bound.fraction:.0f} % kept)"))
    if registration.kept_learned:
        doubts.append(registration.kept_learned)
    apart = registration.checks.get("view_disagreement_mm", 0.0)
    if apart > VIEW_DISAGREEMENT_MM:
        doubts.append(f"the two views place the patient {apart:.0f} mm apart along the axis both see: did the patient move "
                      "between the runs, or are they not one biplane pair?")
    return tuple(doubts)


def _tto_distrusted(learned: Mapping[str, np.ndarray], finals: Mapping[str, np.ndarray], objective: float | None, *,
                    computed_vessels: bool) -> str | None:
    """Why the TTO's result ``finals`` gives way to the networks' estimate ``learned`` (poses per view), worded for
    the record and the flag; None when it is kept. ``objective``: the result's (both views summed)."""
    if computed_vessels:
        moved = [stage_agreement(learned[key], finals[key]) for key in VIEW_KEYS]
        rot, mm = max(m[0] for m in moved), max(m[1] for m in moved)
        if rot > AGREEMENT_DEG or mm > AGREEMENT_MM:
            return APPROXIMATE_VESSELS_NOTE.format(rot=rot, mm=mm)
    if objective is not None and objective > WEAK_OBJECTIVE:
        return WEAK_EVIDENCE_NOTE.format(objective=objective, limit=WEAK_OBJECTIVE)
    return None


def _same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two poses ``(4, 4)`` are one start: rotations within 1e-4, positions within 0.01 mm."""
    return bool(np.allclose(a[:3, :3], b[:3, :3], atol=1e-4) and np.allclose(a[:3, 3], b[:3, 3], atol=0.01))


def stage_agreement(learned: np.ndarray, final: np.ndarray) -> tuple[float, float]:
    """How far the final camera pose ``(4, 4)`` moved from the learned one: the rotation (deg) and
    the shift (mm) of the CTA's centre in the camera frame (:func:`pose_error_components`; a
    rotation about the centre moves the source by hundreds of mm but the patient not at all)."""
    parts = pose_error_components(final, learned)
    return (float(np.hypot(parts["in_plane_rotation_deg"], parts["out_of_plane_rotation_deg"])),
            float(np.hypot(parts["in_plane_mm"], parts["depth_mm"])))


def register_case(
    cta: Volume,
    dsa: Mapping[str, DSARun],
    *,
    models: str | ModelSet | None = None,
    options: RegistrationOptions | None = None,
    cranium_mask: Volume | None = None,
    segmentation: Volume | None = None,
    dsa_masks: Mapping[str, np.ndarray] | None = None,
    progress: ProgressCallback | None = None,
    cancel: CancelCheck | None = None,
) -> CaseRegistration:
    """Register a native CTA (HU) to ``dsa = {"pa": run, "lat": run}``.

    ``models``: a models folder (default: the shipped models) or a :class:`ModelSet` from
    :func:`geopose.nets.load_models` (reused across cases). ``options``: every setting
    (:class:`geopose.options.RegistrationOptions`). Masks are optional label volumes on the
    CTA grid (computed from the CTA when absent). ``progress(stage, fraction, message)`` is
    called throughout; ``cancel()`` returning True stops at the next step
    (:class:`~geopose.register.progress.RegistrationCancelled`). Returns every pose and trace.
    """
    options = options or RegistrationOptions()
    monitor = Monitor(progress, cancel)
    times: dict[str, float] = {}
    notes: list[str] = []
    t_start = time.perf_counter()

    # 1. The case: CTA render volume and masks, preprocessed DSA views.
    backend, device, model_set = resolve_engine(options, models)
    tto_px = options.tto_px or (TTO_PX_CUDA if device.startswith("cuda") else TTO_PX_CPU)
    clip = options.model_clip_percentiles or model_set.clip_percentiles
    case = prepare_case(
        cta, dsa, cranium_mask=cranium_mask, segmentation=segmentation, dsa_masks=dsa_masks, tto_px=tto_px,
        model_clip_percentiles=clip, work_spacing_mm=options.work_spacing_mm, monitor=monitor,
    )
    renderer = make_renderer(case.volume, "torch" if backend == "torch" else "numpy", device)
    tto_renderer = torch_renderer_for(renderer)
    engine = Engine(renderer, model_set, tto_renderer)
    render_px = options.render_px or model_set.render_px
    times["prepare"] = time.perf_counter() - t_start

    # 2. Projection-space calibration (once per CTA).
    with _timed(times, "calibration", engine):
        monitor.step("calibration", 0.0, "rendering the PA calibration DRR")
        calibration = calibrate(renderer, model_set.init, render_px)

    # 3. Calibrated Init per view. One patient pose: the lateral side from the acquisition
    #    angles, the views' estimates fused by what each observes.
    joint = not options.independent_views
    rig = nominal_poses(dsa)
    labels = {key: case.views[key].view_label for key in VIEW_KEYS}
    inits: dict[str, InitEstimate] = {}
    with _timed(times, "init", engine):
        for i, key in enumerate(VIEW_KEYS):
            monitor.step("init", i / 2, f"Init {key.upper()}")
            inits[key] = calibrated_init(case.model_target(key), key == "lat", model_set.init, calibration,
                                         view=labels[key] if joint else None)
    registration = Registration("biplane-rigid" if joint else "independent views", rig)
    if joint:
        implied = {key: patient_pose(inits[key].pose_native, rig[key]) for key in VIEW_KEYS}
        X_init = fuse_patient_poses(implied, rig)
        init_poses = view_poses(X_init, rig)
        registration.checks = {"view_disagreement_mm": axis_disagreement_mm(implied, rig)}
    else:
        init_poses = {key: inits[key].pose_native for key in VIEW_KEYS}

    # 4. Similarity-gated greedy refinement (per view, or of the patient pose from every combination
    #    of the fused and the views' rotations and isocentres, the most similar end kept).
    with _timed(times, "refine", engine):
        targets = {key: case.model_target(key) for key in VIEW_KEYS}
        if joint:
            from_starts = refine_from_starts(renderer, targets, combined_starts(implied, X_init), rig, labels,
                                             model_set.refine, render_px, options.refine_steps, monitor=monitor)
            refined = from_starts.traces
            registration.refine_start, registration.refine_starts = from_starts.start, from_starts.mncc
        else:
            refined = {key: greedy_refine(renderer, targets[key], init_poses[key], inits[key].view, model_set.refine,
                                          render_px, options.refine_steps, monitor) for key in VIEW_KEYS}
    learned = {key: refined[key].pose for key in VIEW_KEYS}
    if joint:
        X_learned = patient_pose(learned["pa"], rig["pa"])
        if options.search:
            with _timed(times, "search", engine):
                registration.search = similarity_search(renderer, targets, X_learned, rig, render_px, monitor=monitor)
            X_learned = registration.search.patient_pose
            learned = view_poses(X_learned, rig)

    # 5. The candidate starts scored by the objective: the DICOM-angle pose, Init (fused), each
    #    view's Init alone (a view's Init can be far off where the other's is right) and Refine
    #    with the search (one patient pose). The TTO (needs PyTorch) runs the distinct starts as a
    #    tournament: all through the coarse steps, then the DICOM angles' run and the best other by
    #    the loss there to the end; the lower final objective wins (the DICOM angles' on a tie), so
    #    the result is never worse, by the objective, than the acquisition's own geometry optimised
    #    alike.
    finals = dict(learned)
    tto_result: TTOResult | None = None
    vessels = case.volume.mask("vessels")
    registration.vessel_evidence = vessels is not None and bool(vessels.any())
    if joint and not registration.vessel_evidence:
        notes.append(NO_VESSELS_NOTE)
    with _timed(times, "tto", engine):
        if joint:
            candidates = {DICOM_START: np.eye(4)}
            if registration.vessel_evidence:
                candidates |= {"Init": X_init, **{f"Init {key.upper()}": implied[key] for key in VIEW_KEYS},
                               SEARCHED_START if registration.search else "Refine": X_learned}
            registration.starts = {name: pair_objective(renderer, view_poses(X, rig), case.views)
                                   for name, X in candidates.items()}
            registration.chosen_start = min(registration.starts, key=registration.starts.get)
            registration.patient_pose = candidates[registration.chosen_start]
            finals = view_poses(registration.patient_pose, rig)
        if options.iterations > 0 and tto_renderer is None:
            notes.append(NO_TORCH_TTO_NOTE)
            monitor.step("tto", 1.0, NO_TORCH_TTO_NOTE)
        elif options.iterations > 0 and joint:
            distinct: dict[str, np.ndarray] = {}
            for name, X in candidates.items():
                if not any(_same_pose(X, Y) for Y in distinct.values()):
                    distinct[name] = X
            registration.tto_runs = test_time_optimise_starts(
                tto_renderer, tto_views(case.views, view_poses(np.eye(4), rig)), distinct, rig,
                TTOSchedule(options.iterations), keep=(DICOM_START,), monitor=monitor)
            # The finalists compared by one objective: the opacified vessels alone, when they were read.
            selection = next((r.vessel_selection for r in registration.tto_runs.values() if r.vessel_selection), None)
            registration.vessel_selection = selection
            judge = renderer if selection is None else make_renderer(selection.volume, renderer.engine, device)
            registration.tto_objective = {name: pair_objective(judge, run.poses, case.views)
                                          for name, run in registration.tto_runs.items() if run.stopped_at is None}
            registration.chosen_start = chosen_result(registration.tto_objective)
            tto_result = registration.tto_runs[registration.chosen_start]
            finals, registration.patient_pose = dict(tto_result.poses), tto_result.patient_pose
        elif options.iterations > 0:
            schedule = replace(PAPER_SCHEDULE, iterations=options.iterations)
            tto_result = test_time_optimise(tto_renderer, tto_views(case.views, finals), schedule, objective=PAPER_OBJECTIVE,
                                            biplanar=options.biplanar, monitor=monitor)
            finals = dict(tto_result.poses)
        if joint and registration.vessel_evidence and tto_result is not None:
            registration.kept_learned = _tto_distrusted(learned, finals, registration.tto_objective.get(registration.chosen_start),
                                                        computed_vessels=segmentation is None) or ""
            if registration.kept_learned:
                notes.append(registration.kept_learned)
                finals, registration.patient_pose = dict(learned), X_learned
                registration.chosen_start = SEARCHED_START if registration.search else "Refine"
        if joint and not registration.vessel_evidence:
            registration.bound = bound_move(registration.patient_pose)
            registration.patient_pose = registration.bound.patient_pose
            finals = view_poses(registration.patient_pose, rig)
    if joint and registration.vessel_evidence and segmentation is not None and tto_result is not None:
        with _timed(times, "mirror", engine):
            monitor.step("mirror", 0.0, "weighing the result against the CTA mirrored left-right")
            registration.mirror = mirror_test(renderer, case.views, registration.patient_pose, rig, device)

    # 6. Scores and quality flags.
    outcomes: dict[str, ViewOutcome] = {}
    with _timed(times, "score", engine):
        for key in VIEW_KEYS:
            score, dice = score_view(renderer, finals[key], case.views[key])
            evidence = view_evidence(renderer, finals[key], case.views[key])
            # the vessel NCC grades a pose only against a given segmentation: a computed mask holds veins and bone
            # rims, and its NCC stays low at the truth (the demo phantom: 0.05-0.13 at 2 mm mPCD)
            quality: Quality = assess(score, dice, *stage_agreement(learned[key], finals[key]),
                                      evidence=evidence if segmentation is not None else None,
                                      mirror=registration.mirror,
                                      doubts=_consistency_doubts(key, inits[key], labels[key], registration))
            outcomes[key] = ViewOutcome(key, case.views[key], inits[key], init_poses[key], refined[key], finals[key], score,
                                        dice, quality, learned[key] if registration.search else None, evidence)
    times["total"] = time.perf_counter() - t_start
    monitor.step("done", 1.0, "registration finished" + (" (" + notes[0] + ")" if notes else ""))
    return CaseRegistration(cta, case.labels_source, calibration, outcomes, tto_result, times, options,
                            engine.describe(options, case), registration, renderer, notes)
