"""GeoPose registration stages: calibration, calibrated Init, gated refinement,
test-time optimisation, the whole-case pipeline, its result record and pictures."""

from .calibration import Calibration, InitEstimate, calibrate, calibrated_init, render_model_view
from .pipeline import (
    CaseRegistration, PreparedCase, RegistrationOptions, ViewOutcome, case_labels, prepare_case, register_case,
    resolve_device,
)
from .progress import ConsoleProgress, Monitor, RegistrationCancelled
from .quality import Quality, assess
from .refine import Proposal, RefineTrace, greedy_refine
from .tto import TTOResult, TTOView, biplanar_penalty, test_time_optimise

__all__ = [
    "Calibration", "CaseRegistration", "ConsoleProgress", "InitEstimate", "Monitor", "PreparedCase", "Proposal", "Quality",
    "RefineTrace", "RegistrationCancelled", "RegistrationOptions", "TTOResult", "TTOView", "ViewOutcome", "assess",
    "biplanar_penalty", "calibrate", "calibrated_init", "case_labels", "greedy_refine", "prepare_case", "register_case",
    "render_model_view", "resolve_device", "test_time_optimise",
]
