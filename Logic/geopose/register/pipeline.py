"""The GeoPose registration of one case: :func:`register_case`, read top to bottom.

By default the two runs are one biplane acquisition: one patient pose ``X`` places both C-arms
(``T_v = X @ A_v``, ``A_v`` from each run's DICOM geometry; ``biplane.py``). The stages, each in
its own module:

1. ``engine.start_case``: the engine (renderer and networks) and the case: CTA render volume (its
   masks made on another thread meanwhile), each DSA run's MAP, cranium mask and preprocessed images (``case.py``);
2. ``calibration.calibrate``: one DRR of the native CTA at the PA isopose and one Init pass give
   the canonical -> native frame transfer;
3. ``init.biplane_init``: calibrated Init on each view's MAP, fused into one patient pose;
4. ``refine.refine_from_starts``: similarity-gated greedy Refine from every combination of the
   Init estimates' rotations and isocentres (``starts.refine_starts``), the most similar end kept;
5. ``search.similarity_search``: the patient pose's shift and in-plane turns by the same score;
   its result is the networks' estimate, handed to ``preliminary`` (a front end shows it meanwhile);
6. ``vessel_image.choose_vessel_images``: the vessel image of each run the objective compares (the bolus-weighted
   frames, or the run's first half where the CTA's vessels at the estimate clearly prefer it);
   ``starts.candidate_starts`` and ``tournament.run_tournament``: the test-time optimisation
   (PyTorch; skipped with a note without it) from every distinct candidate start, the result of
   lowest objective kept, the DICOM angles' on a tie; ``continuation.continued``: a result that turned far from
   its start optimised once more from where it ended;
7. ``trust.kept_result``: the networks' estimate is kept where the TTO's result is not to be
   trusted (on a given segmentation its vessel NCC per view, ``evidence.view_evidence``, is read for
   that), and without vessel evidence the move from the DICOM angles is bounded;
8. ``mirror.mirror_test``: the result weighed against the CTA mirrored left-right, optimised from the
   networks' estimate; ``pairing.pairing_test``: whether the CTA's vessels fit the runs' as tightly as one patient's do;
9. ``scoring.score_views``: final mNCC, silhouette Dice and quality flag per view.

``independent_views=True`` runs the published pipeline instead (``published.py``). Poses between
stages are float64 numpy ``(4, 4)`` camera-to-world in the centred native CTA frame (mm). The CLI,
the demo, the benchmark and the Slicer module all call :func:`register_case`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping

import numpy as np

from ..dsa import DSARun
from ..dsa.subtraction import unsubtracted_notes
from ..nets.predictors import ModelSet
from ..options import RegistrationOptions
from ..volume import Volume
from .biplane import nominal_poses, patient_pose, view_poses
from .calibration import calibrate
from .continuation import continued
from .engine import NO_TORCH_TTO_NOTE, StageClock, engine_notes, start_case
from .evidence import view_evidence
from .init import biplane_init
from .mirror import mirror_test
from .opacified import selection_judge
from .pairing import NOT_RUN_NOTE as PAIRING_NOT_RUN_NOTE, pairing_test
from .progress import CancelCheck, Monitor, PreliminaryCallback, ProgressCallback, hand_over_estimate
from .published import register_published
from .refine import refine_from_starts
from .results import CaseRegistration, Registration
from .scoring import score_views
from .search import similarity_search
from .starts import REFINED_START, SEARCHED_START, candidate_starts, refine_starts
from .tournament import run_tournament
from .trust import NO_VESSELS_NOTE, kept_result
from .vessel_image import choose_vessel_images

__all__ = ["register_case"]


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
    preliminary: PreliminaryCallback | None = None,
) -> CaseRegistration:
    """Register a native CTA (HU) to ``dsa = {"pa": run, "lat": run}``.

    ``models``: a models folder (default: the shipped models) or a :class:`ModelSet` from
    :func:`geopose.nets.load_models` (reused across cases). ``options``: every setting
    (:class:`geopose.options.RegistrationOptions`). Masks are optional label volumes on the
    CTA grid (computed from the CTA when absent). ``progress(stage, fraction, message)`` is
    called throughout; ``cancel()`` returning True stops at the next step
    (:class:`~geopose.register.progress.RegistrationCancelled`). ``preliminary(result)`` receives the networks'
    estimate as soon as it exists (a :class:`~geopose.register.progress.Preliminary`), before the test-time
    optimisation. Returns every pose and trace.
    """
    options = options or RegistrationOptions()
    masks = {"cranium_mask": cranium_mask, "segmentation": segmentation, "dsa_masks": dsa_masks}
    if options.independent_views:
        return register_published(cta, dsa, models=models, options=options, progress=progress, cancel=cancel,
                                  preliminary=preliminary, **masks)
    monitor, clock, notes, rig = Monitor(progress, cancel), StageClock(), engine_notes() + unsubtracted_notes(dsa), nominal_poses(dsa)
    with clock("prepare"):
        engine, case = start_case(cta, dsa, options, models, monitor=monitor, **masks)
    renderer, nets, render_px = engine.renderer, engine.models, engine.render_px
    with clock("calibration", engine):
        calibration = calibrate(renderer, nets.init, render_px, monitor)
    with clock("init", engine):
        init = biplane_init(case, nets.init, calibration, rig, monitor)
    estimator = renderer.sampling(options.estimate_voxel_per_pixel)  # the levels Refine and the search render
    with clock("refine", engine):
        refined = refine_from_starts(estimator, case.model_targets(), refine_starts(init), rig, case.view_labels(),
                                     nets.refine, render_px, options.refine, monitor=monitor)
    learned = {key: trace.pose for key, trace in refined.traces.items()}
    estimate, X_learned, search = REFINED_START, patient_pose(learned["pa"], rig["pa"]), None
    if options.search.enabled:
        with clock("search", engine):
            search = similarity_search(estimator, case.model_targets(), X_learned, rig, render_px, options.search.schedule,
                                       monitor)
        estimate, X_learned, learned = SEARCHED_START, search.patient_pose, view_poses(search.patient_pose, rig)
    hand_over_estimate(preliminary, learned, clock.elapsed_s())
    tournament, measured = None, None
    with clock("tto", engine):  # the CTA's masks, begun on another thread at prepare, are awaited here
        monitor.step("tto", 0.0, "the CTA's cranium and vessel masks")
        vessel_evidence = case.vessel_evidence
        notes += [] if vessel_evidence else [NO_VESSELS_NOTE]
        vessel_images = {}
        if vessel_evidence:  # the vessel image each run's objective compares, picked by the CTA's vessels at the estimate
            views, vessel_images = choose_vessel_images(renderer, case.views, learned)
            case = replace(case, views=views)
        starts = candidate_starts(renderer, case.views, rig, init, {estimate: X_learned}, options.objective,
                                  vessel_evidence=vessel_evidence)
        if options.tto.iterations > 0 and engine.tto_renderer is None:
            notes.append(NO_TORCH_TTO_NOTE)
            monitor.step("tto", 1.0, NO_TORCH_TTO_NOTE)
        elif options.tto.iterations > 0:
            tournament = run_tournament(renderer, engine.tto_renderer, case.views, starts, rig, options.tto, options.objective,
                                        monitor, estimate=(estimate, X_learned))
            tournament = continued(renderer, engine.tto_renderer, case.views, tournament, rig, options.tto, options.objective,
                                   monitor)
            if segmentation is not None:  # the result's evidence, (pose, terms) per view: trust and scoring read it
                measured = {key: (pose, view_evidence(renderer, pose, case.views[key], options.objective))
                            for key, pose in tournament.result.poses.items()}
        kept = kept_result(starts, tournament, (estimate, X_learned, learned), rig, vessel_evidence=vessel_evidence,
                           computed_vessels=segmentation is None,
                           tto_vessel_ncc=None if measured is None else {key: ev.vessel_ncc for key, (_, ev) in measured.items()})
    notes += [kept.kept_learned] if kept.kept_learned else []
    mirror, pairing = None, None
    if vessel_evidence and tournament is not None:
        with clock("mirror", engine):
            mirror = mirror_test(renderer, case.views, tournament, X_learned, rig,
                                 options.objective, engine.device, monitor)
        notes += [mirror.note] if mirror.note else []
        if case.arteries_classified or segmentation is not None:  # a mask of mostly arteries (pairing.py)
            with clock("pairing", engine):
                pairing = pairing_test(selection_judge(renderer, tournament.vessel_selection), tournament.result.poses,
                                       case.views, given_segmentation=segmentation is not None)
        else:
            notes.append(PAIRING_NOT_RUN_NOTE)
    registration = Registration(
        "biplane-rigid", rig, patient_pose=kept.patient_pose, starts=dict(starts.objectives), chosen_start=kept.start,
        tto_runs=dict(tournament.runs) if tournament else {}, tto_objective=dict(tournament.objectives) if tournament else {},
        vessel_selection=tournament.vessel_selection if tournament else None,
        checks={"view_disagreement_mm": init.view_disagreement_mm}, refine_start=refined.start, refine_starts=refined.mncc,
        search=search, vessel_evidence=vessel_evidence, bound=kept.bound, mirror=mirror, pairing=pairing,
        kept_learned=kept.kept_learned,
        vessel_images=vessel_images)
    with clock("score", engine):
        outcomes = score_views(renderer, case, registration, inits=init.views, init_poses=view_poses(init.patient_pose, rig),
                               refined=refined.traces, learned=learned, finals=kept.poses, searched=search is not None,
                               given_vessels=segmentation is not None, objective=options.objective, measured=measured)
    monitor.step("done", 1.0, "registration finished" + (" (" + notes[0] + ")" if notes else ""))
    return CaseRegistration(cta, case.labels_source, calibration, outcomes, tournament.result if tournament else None,
                            clock.total(), options, engine.describe(options, case), registration, renderer, notes,
                            work=clock.work)
