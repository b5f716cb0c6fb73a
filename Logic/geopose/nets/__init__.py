"""GeoPose networks: Init and Refine modules, model files and manifest, checkpoint import,
ONNX export, and the predictors the registration runs (torch or onnxruntime)."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "decoding": ("decode_init_pose", "mirror_averaged_logits", "residual_from_raw", "select_view"),
        "model_io": ("find_model_files", "load_model", "read_model_header", "save_model"),
        "onnx_export": ("export_onnx",),
        "models": (
            "PUBLISHED_INIT_CONFIG", "PUBLISHED_REFINE_CONFIG", "InitNet", "NetConfig", "RefineNet", "build_model",
            "parameter_count",
        ),
        "predictors": (
            "InitPredictor", "ModelSet", "RefinePredictor", "load_models", "onnx_predictors", "torch_predictors",
        ),
        "resnet": ("BackboneConfig", "ResNetEncoder"),
    },
)
