"""ONNX export of the GeoPose networks.

Graphs (float32, dynamic batch, fixed image size given at export):

- Init: ``image (B,1,H,W)`` -> ``raw_pose (B,3,6)`` (the raw pose for each view
  label LAT-, PA, LAT+) and ``view_logits (B,3)``. The view rule and the decoding
  run outside the graph (:mod:`.decoding`), identically for both backends.
- Refine: ``target, render (B,1,H,W)`` and ``view (B,) int64`` -> ``raw_residual (B,6)``.

Inputs are expected min-max normalised; the runners apply :func:`normalize_minmax`.
"""

from __future__ import annotations

import io
import os
import warnings
from pathlib import Path

import onnx
import torch
from torch import Tensor, nn

from ..contract import MODEL_DETECTOR_PX
from .models import InitNet, RefineNet

ONNX_OPSET = 17
#: Key of the ONNX metadata entry that records the network kind.
KIND_METADATA_KEY = "geopose_kind"


class _InitGraph(nn.Module):
    def __init__(self, net: InitNet) -> None:
        super().__init__()
        self.model = net

    def forward(self, image: Tensor) -> tuple[Tensor, Tensor]:
        return self.model.forward_all_views(image)


def export_onnx(
    module: InitNet | RefineNet, path: str | os.PathLike | None = None, *, image_px: int = MODEL_DETECTOR_PX
) -> bytes | Path:
    """Export ``module`` (float32, eval mode) for ``image_px`` square images; to ``path``, or bytes if ``None``."""
    if not isinstance(module, (InitNet, RefineNet)):
        raise TypeError(f"export_onnx takes an InitNet or RefineNet, got {type(module).__name__}")
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
    entry = proto.metadata_props.add()
    entry.key, entry.value = KIND_METADATA_KEY, module.config.kind
    data = proto.SerializeToString()
    if path is None:
        return data
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def onnx_kind(model: bytes | str | os.PathLike) -> str:
    """The network kind (``init``/``refine``) recorded by :func:`export_onnx`."""
    proto = onnx.load_from_string(model) if isinstance(model, bytes) else onnx.load(os.fspath(model))
    for entry in proto.metadata_props:
        if entry.key == KIND_METADATA_KEY:
            return entry.value
    raise ValueError(f"the ONNX model has no '{KIND_METADATA_KEY}' entry; export it with geopose.nets.export_onnx")
