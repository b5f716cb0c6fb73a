"""GeoPose networks: Init and Refine modules, model files, checkpoint import, ONNX and backends."""

from ..lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "backend": (
            "InitPredictor", "OnnxInitPredictor", "OnnxRefinePredictor", "RefinePredictor", "make_predictors",
        ),
        "decoding": ("decode_init_pose", "mirror_averaged_logits", "residual_from_raw", "select_view"),
        "model_io": ("find_model_files", "load_model", "read_model_header", "save_model"),
        "onnx_export": ("export_onnx",),
        "models": (
            "PUBLISHED_INIT_CONFIG", "PUBLISHED_REFINE_CONFIG", "InitNet", "NetConfig", "RefineNet", "build_model",
            "parameter_count",
        ),
        "preprocess": ("normalize_minmax",),
        "resnet": ("BackboneConfig", "ResNetEncoder"),
    },
)
