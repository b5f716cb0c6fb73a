"""GeoPose networks: Init and Refine modules, model files, checkpoint import, ONNX and backends."""

from .backend import InitPredictor, OnnxInitPredictor, OnnxRefinePredictor, RefinePredictor, make_predictors
from .decoding import decode_init_pose, residual_from_raw, select_view
from .model_io import find_model_files, load_model, read_model_header, save_model
from .onnx_export import export_onnx
from .models import (
    PUBLISHED_INIT_CONFIG,
    PUBLISHED_REFINE_CONFIG,
    InitNet,
    NetConfig,
    RefineNet,
    build_model,
    parameter_count,
)
from .preprocess import normalize_minmax
from .resnet import BackboneConfig, ResNetEncoder

__all__ = [
    "InitPredictor",
    "OnnxInitPredictor",
    "OnnxRefinePredictor",
    "RefinePredictor",
    "export_onnx",
    "make_predictors",
    "BackboneConfig",
    "InitNet",
    "NetConfig",
    "PUBLISHED_INIT_CONFIG",
    "PUBLISHED_REFINE_CONFIG",
    "RefineNet",
    "ResNetEncoder",
    "build_model",
    "decode_init_pose",
    "find_model_files",
    "load_model",
    "normalize_minmax",
    "parameter_count",
    "read_model_header",
    "residual_from_raw",
    "save_model",
    "select_view",
]
