"""Inference backends: the same predict API on torch modules or onnxruntime sessions."""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from .decoding import as_view_labels, decode_init_pose, residual_from_raw, select_view
from .model_io import load_model, model_files
from .onnx_export import export_onnx, onnx_kind
from .preprocess import normalize_minmax

BACKENDS = ("torch", "onnxruntime")


class InitPredictor(Protocol):
    def predict(self, image: Tensor, is_lateral: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """image ``(B,1,H,W)`` -> pose ``(B,4,4)`` (mm, centred frame), view ``(B,)``, logits ``(B,3)``."""
        ...


class RefinePredictor(Protocol):
    def predict_residual(self, target: Tensor, render: Tensor, view: Tensor | int) -> Tensor:
        """(target, render ``(B,1,H,W)``, view) -> residual ``D`` ``(B,4,4)``; apply ``inverse(D) @ T``."""
        ...


def _session(model: bytes | str | os.PathLike, device: torch.device):
    import onnxruntime as ort

    providers = ["CPUExecutionProvider"]
    if device.type == "cuda":
        if "CUDAExecutionProvider" in ort.get_available_providers():
            providers.insert(0, "CUDAExecutionProvider")
        else:
            warnings.warn("onnxruntime has no CUDA provider here; running on CPU (install onnxruntime-gpu for CUDA)")
    source = model if isinstance(model, bytes) else os.fspath(model)
    return ort.InferenceSession(source, providers=providers)


def _numpy(x: Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).contiguous().numpy()


def _check_graph_images(session, name: str, image: Tensor) -> None:
    """Images must be ``(B, 1, H, W)`` with the (H, W) the graph was exported for."""
    expected = tuple(session.get_inputs()[0].shape[1:])
    if image.ndim != 4 or tuple(image.shape[1:]) != expected:
        raise ValueError(
            f"{name} must be a (B, {', '.join(map(str, expected))}) batch for this ONNX model, got shape {tuple(image.shape)}; "
            "resample to the model detector or export the model for this size"
        )


class OnnxInitPredictor:
    """GeoPose-Init on onnxruntime (graph from :func:`export_onnx`)."""

    def __init__(self, model: bytes | str | os.PathLike, device: str | torch.device = "cpu") -> None:
        if onnx_kind(model) != "init":
            raise ValueError("this ONNX model is not a GeoPose-Init network")
        self.device = torch.device(device)
        self.session = _session(model, self.device)

    def predict(self, image: Tensor, is_lateral: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        _check_graph_images(self.session, "image", image)
        raw_all, logits = self.session.run(None, {"image": _numpy(normalize_minmax(image))})
        raw_all = torch.from_numpy(raw_all).to(image.device)
        logits = torch.from_numpy(logits).to(image.device)
        view = select_view(logits, is_lateral)
        raw = raw_all[torch.arange(raw_all.shape[0], device=image.device), view]
        return decode_init_pose(raw, view), view, logits


class OnnxRefinePredictor:
    """GeoPose-Refine on onnxruntime (graph from :func:`export_onnx`)."""

    def __init__(self, model: bytes | str | os.PathLike, device: str | torch.device = "cpu") -> None:
        if onnx_kind(model) != "refine":
            raise ValueError("this ONNX model is not a GeoPose-Refine network")
        self.device = torch.device(device)
        self.session = _session(model, self.device)

    def predict_residual(self, target: Tensor, render: Tensor, view: Tensor | int) -> Tensor:
        for name, image in (("target", target), ("render", render)):
            _check_graph_images(self.session, name, image)
        if target.shape[0] != render.shape[0]:
            raise ValueError(f"target has {target.shape[0]} images and render {render.shape[0]}; pass pairs")
        labels = as_view_labels(view, target.shape[0]).cpu().numpy()
        (raw,) = self.session.run(
            None,
            {"target": _numpy(normalize_minmax(target)), "render": _numpy(normalize_minmax(render)), "view": labels},
        )
        return residual_from_raw(torch.from_numpy(raw).to(target.device))


def _model_files(source: str | os.PathLike | Mapping[str, str | os.PathLike]) -> dict[str, Path]:
    if isinstance(source, Mapping):
        files = {kind: Path(source[kind]) for kind in ("init", "refine") if kind in source}
        if set(files) != {"init", "refine"}:
            raise ValueError(f"model files must be given for both 'init' and 'refine', got {sorted(source)}")
        return files
    return model_files(source)


def make_predictors(
    source: str | os.PathLike | Mapping[str, str | os.PathLike],
    backend: str = "torch",
    device: str | torch.device = "cpu",
) -> tuple[InitPredictor, RefinePredictor]:
    """Init and Refine predictors from a model directory or ``{"init": file, "refine": file}``.

    Files are GeoPose ``.pt`` model files; with ``backend="onnxruntime"`` they may
    also be ``.onnx`` files from :func:`export_onnx` (``.pt`` files are exported in memory).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    files = _model_files(source)
    device = torch.device(device)
    if backend == "torch":
        for path in files.values():
            if path.suffix == ".onnx":
                raise ValueError(f"{path} is an ONNX file; use backend='onnxruntime' or pass the .pt model file")
        init, refine = (load_model(files[k], device) for k in ("init", "refine"))
        for kind, module in (("init", init), ("refine", refine)):
            if module.config.kind != kind:
                raise ValueError(f"{files[kind]} holds a {module.config.kind} network, expected {kind}")
        return init, refine
    models = {k: (p if p.suffix == ".onnx" else export_onnx(load_model(p))) for k, p in files.items()}
    return OnnxInitPredictor(models["init"], device), OnnxRefinePredictor(models["refine"], device)
