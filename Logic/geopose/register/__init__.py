"""GeoPose registration: the one pipeline (``pipeline.register_case``) and its stages
(case preparation, calibration, calibrated Init, gated refinement, similarity
search, test-time optimisation), result dataclasses and record, pictures and the ``register`` command."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "calibration": ("calibrate", "calibrated_init", "render_model_view"),
        "case": ("VIEW_KEYS", "PreparedCase", "prepare_case"),
        "pipeline": ("NO_TORCH_TTO_NOTE", "register_case", "resolve_engine", "score_view", "tto_views"),
        "progress": ("ConsoleProgress", "Monitor", "RegistrationCancelled"),
        "quality": ("Quality", "assess"),
        "refine": ("greedy_refine", "greedy_refine_biplane", "refine_from_starts"),
        "search": ("similarity_search",),
        "results": ("Calibration", "CaseRegistration", "InitEstimate", "Proposal", "RefineTrace", "SearchTrace",
                    "ViewOutcome"),
        "tto": ("PAPER_SCHEDULE", "TTOResult", "TTOSchedule", "TTOView", "biplanar_penalty", "test_time_optimise"),
        "objective": ("Objective", "PAPER_OBJECTIVE", "objective_value"),
        "biplane": ("Observability", "combined_starts", "fuse_patient_poses", "nominal_poses", "patient_pose", "view_poses"),
    },
)
