"""Inference backends: the same predict API on torch modules or onnxruntime sessions."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from .decoding import as_view_labels
from .manifest import lists_format, verify_manifest
from .model_io import load_model, model_files
from .onnx_export import export_onnx
from .onnx_runtime import OnnxInit, OnnxRefine

BACKENDS = ("torch", "onnxruntime")


class InitPredictor(Protocol):
    def predict(self, image: Tensor, is_lateral: Tensor | None = None, mirror: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """image ``(B,1,H,W)`` -> pose ``(B,4,4)`` (mm, centred frame), view ``(B,)``, logits ``(B,3)``
        (``mirror``: averaged with the column-mirrored images' logits)."""
        ...


class RefinePredictor(Protocol):
    def predict_residual(self, target: Tensor, render: Tensor, view: Tensor | int) -> Tensor:
        """(target, render ``(B,1,H,W)``, view) -> residual ``D`` ``(B,4,4)``; apply ``inverse(D) @ T``."""
        ...


def _numpy(x: Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).contiguous().numpy()


class OnnxInitPredictor:
    """GeoPose-Init on onnxruntime behind the torch predictor API (:class:`OnnxInit` inside)."""

    def __init__(self, model: bytes | str | os.PathLike, device: str | torch.device = "cpu") -> None:
        self.device = torch.device(device)
        self.runner = OnnxInit(model, use_cuda=self.device.type == "cuda")

    def predict(self, image: Tensor, is_lateral: Tensor | None = None, mirror: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        lateral = None if is_lateral is None else _numpy(torch.as_tensor(is_lateral)).astype(bool)
        pose, view, logits = self.runner.predict(_numpy(image), lateral, mirror)
        return (
            torch.from_numpy(pose).to(image.device, image.dtype),
            torch.from_numpy(view).to(image.device),
            torch.from_numpy(logits).to(image.device),
        )


class OnnxRefinePredictor:
    """GeoPose-Refine on onnxruntime behind the torch predictor API (:class:`OnnxRefine` inside)."""

    def __init__(self, model: bytes | str | os.PathLike, device: str | torch.device = "cpu") -> None:
        self.device = torch.device(device)
        self.runner = OnnxRefine(model, use_cuda=self.device.type == "cuda")

    def predict_residual(self, target: Tensor, render: Tensor, view: Tensor | int) -> Tensor:
        labels = as_view_labels(view, target.shape[0]).cpu().numpy()
        residual = self.runner.predict_residual(_numpy(target), _numpy(render), labels)
        return torch.from_numpy(residual).to(target.device, target.dtype)


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
    also be ``.onnx`` files from :func:`export_onnx`; a folder whose manifest lists ONNX
    graphs runs those, otherwise ``.pt`` files are exported in memory.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    device = torch.device(device)
    if backend == "onnxruntime" and not isinstance(source, Mapping) and lists_format(source, "onnx"):
        graphs = verify_manifest(source, "onnx")  # the shipped graphs
        return OnnxInitPredictor(graphs["init"], device), OnnxRefinePredictor(graphs["refine"], device)
    files = _model_files(source)
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
