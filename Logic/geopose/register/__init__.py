"""GeoPose registration: the one pipeline (``pipeline.register_case``) and its stages, each in its
own module (engine and case, calibration, Init, greedy Refine, similarity search, candidate starts,
the TTO and its tournament, the trust rules, the mirror test, scoring), the published
independent-views pipeline (``published.py``), result dataclasses and record, pictures and the
``register`` command."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "calibration": ("calibrate", "calibrated_init", "render_model_view"),
        "case": ("VIEW_KEYS", "PreparedCase", "prepare_case"),
        "engine": ("NO_TORCH_TTO_NOTE", "resolve_engine"),
        "pipeline": ("register_case",),
        "progress": ("ConsoleProgress", "Monitor", "Preliminary", "RegistrationCancelled"),
        "quality": ("Quality", "assess"),
        "refine": ("greedy_refine", "refine_from_starts"),
        "scoring": ("score_view",),
        "search": ("similarity_search",),
        "results": ("Calibration", "CaseRegistration", "InitEstimate", "Proposal", "RefineTrace", "SearchTrace",
                    "ViewOutcome"),
        "tto": ("PAPER_SCHEDULE", "TTOResult", "TTOSchedule", "TTOView", "biplanar_penalty", "test_time_optimise",
                "tto_views"),
        "objective": ("Objective", "PAPER_OBJECTIVE", "objective_value"),
        "biplane": ("Observability", "fuse_patient_poses", "nominal_poses", "patient_pose", "view_poses"),
    },
)
