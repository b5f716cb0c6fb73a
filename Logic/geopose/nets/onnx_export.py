"""ONNX export of the GeoPose networks.

Graphs (float32, dynamic batch, fixed image size given at export):

- Init: ``image (B,1,H,W)`` -> ``raw_pose (B,3,6)`` (the raw pose for each view
  label LAT-, PA, LAT+) and ``view_logits (B,3)``. The view rule and the decoding
  run outside the graph (:mod:`.decoding`), identically for both backends.
- Refine: ``target, render (B,1,H,W)`` and ``view (B,) int64`` -> ``raw_residual (B,6)``.

Inputs are expected min-max normalised; the predictors (``predictors.py``) apply
:func:`normalize_minmax`. ``weights="float16"`` stores the weights in half precision
with a Cast to float32 in front of their users (half the file; the arithmetic stays float32).
"""

from __future__ import annotations

import io
import os
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import Tensor, nn

from ..contract import MODEL_DETECTOR_PX
from .models import InitNet, RefineNet
from .predictors import KIND_METADATA_KEY

ONNX_OPSET = 17
WEIGHT_DTYPES = ("float32", "float16")


class _InitGraph(nn.Module):
    def __init__(self, net: InitNet) -> None:
        super().__init__()
        self.model = net

    def forward(self, image: Tensor) -> tuple[Tensor, Tensor]:
        return self.model.forward_all_views(image)


def _store_half(graph: onnx.GraphProto) -> None:
    """Float32 weights -> float16 initializers, each cast back to float32 under its old name."""
    casts, kept = [], []
    for init in graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT:
            kept.append(init)
            continue
        half = onnx.numpy_helper.from_array(onnx.numpy_helper.to_array(init).astype(np.float16), f"{init.name}__float16")
        kept.append(half)
        casts.append(onnx.helper.make_node("Cast", [half.name], [init.name], to=onnx.TensorProto.FLOAT))
    nodes = casts + list(graph.node)
    del graph.initializer[:], graph.node[:]
    graph.initializer.extend(kept)
    graph.node.extend(nodes)


def export_onnx(
    module: InitNet | RefineNet,
    path: str | os.PathLike | None = None,
    *,
    image_px: int = MODEL_DETECTOR_PX,
    weights: str = "float32",
) -> bytes | Path:
    """Export ``module`` (eval mode) for ``image_px`` square images, weights stored as
    ``weights`` (``float32`` or ``float16``); to ``path``, or bytes if ``None``."""
    if not isinstance(module, (InitNet, RefineNet)):
        raise TypeError(f"export_onnx takes an InitNet or RefineNet, got {type(module).__name__}")
    if weights not in WEIGHT_DTYPES:
        raise ValueError(f"weights must be one of {WEIGHT_DTYPES}, got {weights!r}")
    was_training = module.training
    module = module.eval()
    device = next(module.parameters()).device
    image = torch.zeros(1, 1, image_px, image_px, device=device)
    if isinstance(module, InitNet):
        graph: nn.Module = _InitGraph(module)
        args: tuple = (image,)
        inputs, outputs = ["image"], ["raw_pose", "view_logits"]
    else:
        graph = module
        args = (image, image.clone(), torch.ones(1, dtype=torch.int64, device=device))
        inputs, outputs = ["target", "render", "view"], ["raw_residual"]
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter announces its deprecation
        torch.onnx.export(
            graph,
            args,
            buffer,
            dynamo=False,
            input_names=inputs,
            output_names=outputs,
            dynamic_axes={name: {0: "batch"} for name in inputs + outputs},
            opset_version=ONNX_OPSET,
        )
    module.train(was_training)
    proto = onnx.load_from_string(buffer.getvalue())
    if weights == "float16":
        _store_half(proto.graph)
    entry = proto.metadata_props.add()
    entry.key, entry.value = KIND_METADATA_KEY, module.config.kind
    data = proto.SerializeToString()
    if path is None:
        return data
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path
