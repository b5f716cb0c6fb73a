"""The published pipeline (paper section 2.3): each view registered on its own.

Calibration, calibrated Init per view (its side read by the network), similarity-gated greedy
Refine per view, then the paper's test-time optimisation of each view's own pose (the paper's
objective and schedule, optionally with the PA/lateral orthogonality term). Run it with
``RegistrationOptions(independent_views=True)``; ``pipeline.register_case`` sends it here.
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
from .biplane import nominal_poses
from .calibration import calibrate
from .case import VIEW_KEYS
from .engine import NO_TORCH_TTO_NOTE, StageClock, engine_notes, start_case
from .init import init_views
from .objective import PAPER_OBJECTIVE
from .progress import CancelCheck, Monitor, PreliminaryCallback, ProgressCallback, hand_over_estimate
from .refine import greedy_refine
from .results import CaseRegistration, Registration
from .scoring import score_views
from .tto import PAPER_SCHEDULE, test_time_optimise, tto_views

__all__ = ["register_published"]


def register_published(
    cta: Volume, dsa: Mapping[str, DSARun], *, models: str | ModelSet | None, options: RegistrationOptions,
    cranium_mask: Volume | None = None, segmentation: Volume | None = None, dsa_masks: Mapping[str, np.ndarray] | None = None,
    progress: ProgressCallback | None = None, cancel: CancelCheck | None = None,
    preliminary: PreliminaryCallback | None = None,
) -> CaseRegistration:
    """Register each view of ``dsa`` to ``cta`` on its own (arguments as ``pipeline.register_case``)."""
    monitor, clock, notes = Monitor(progress, cancel), StageClock(), engine_notes() + unsubtracted_notes(dsa)
    with clock("prepare"):
        engine, case = start_case(cta, dsa, options, models, cranium_mask=cranium_mask, segmentation=segmentation,
                                  dsa_masks=dsa_masks, monitor=monitor)
    with clock("calibration", engine):
        calibration = calibrate(engine.renderer, engine.models.init, engine.render_px, monitor)
    with clock("init", engine):
        inits = init_views(case, engine.models.init, calibration, fix_side=False, monitor=monitor)
    with clock("refine", engine):
        refined = {key: greedy_refine(engine.renderer, case.model_target(key), inits[key].pose_native, inits[key].view,
                                      engine.models.refine, engine.render_px, options.refine.steps, monitor)
                   for key in VIEW_KEYS}
    learned = {key: refined[key].pose for key in VIEW_KEYS}
    hand_over_estimate(preliminary, learned, clock.elapsed_s())
    finals, tto = dict(learned), None
    with clock("tto", engine):
        if options.tto.iterations > 0 and engine.tto_renderer is None:
            notes.append(NO_TORCH_TTO_NOTE)
            monitor.step("tto", 1.0, NO_TORCH_TTO_NOTE)
        elif options.tto.iterations > 0:
            tto = test_time_optimise(engine.tto_renderer, tto_views(case.views, learned),
                                     replace(PAPER_SCHEDULE, iterations=options.tto.iterations), objective=PAPER_OBJECTIVE,
                                     biplanar=options.biplanar, monitor=monitor)
            finals = dict(tto.poses)
    registration = Registration("independent views", nominal_poses(dsa), vessel_evidence=case.vessel_evidence)
    with clock("score", engine):
        outcomes = score_views(engine.renderer, case, registration, inits=inits,
                               init_poses={key: inits[key].pose_native for key in VIEW_KEYS}, refined=refined,
                               learned=learned, finals=finals, searched=False, given_vessels=segmentation is not None)
    monitor.step("done", 1.0, "registration finished" + (" (" + notes[0] + ")" if notes else ""))
    return CaseRegistration(cta, case.labels_source, calibration, outcomes, tto, clock.total(), options,
                            engine.describe(options, case), registration, engine.renderer, notes,
                            work=clock.work)
