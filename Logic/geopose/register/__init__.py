"""GeoPose registration stages: calibration, calibrated Init, gated refinement,
test-time optimisation, the whole-case pipeline (torch, or numpy + onnxruntime),
its result record and pictures."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "calibration": ("calibrate", "calibrated_init", "render_model_view"),
        "gating": ("gated_refinement",),
        "case": ("VIEW_KEYS", "case_labels", "prepare_views"),
        "numpy_pipeline": ("register_case_numpy",),
        "pipeline": ("PreparedCase", "prepare_case", "register_case", "resolve_device"),
        "progress": ("ConsoleProgress", "Monitor", "RegistrationCancelled"),
        "quality": ("Quality", "assess"),
        "refine": ("greedy_refine",),
        "results": (
            "Calibration", "CaseRegistration", "InitEstimate", "Proposal", "RefineTrace", "RegistrationOptions",
            "ViewOutcome",
        ),
        "tto": ("TTOResult", "TTOView", "biplanar_penalty", "test_time_optimise"),
    },
)
