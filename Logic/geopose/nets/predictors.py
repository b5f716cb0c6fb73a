"""The networks as the registration runs them: numpy in, numpy out, on torch or onnxruntime.

:func:`load_models` reads a models folder (the shipped one by default), checks every
file against its manifest, and returns a :class:`ModelSet`: an :class:`InitPredictor`,
a :class:`RefinePredictor` and what the manifest says the networks expect (the size
their DRRs were rendered at, the MAP clip). Images are ``(B, 1, 256, 256)`` float32
(min-max applied here); poses are camera-to-world ``(B, 4, 4)`` float64 in the
centred CTA frame (mm); decoding is :mod:`geopose.nets.decoding`, the same for both
runtimes. Only the forward pass is written twice: a torch module or an onnxruntime
session.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .. import contract as C
from ..errors import InputError
from ..resources import default_models_dir
from .decoding import decode_init_pose, mirror_averaged_logits, residual_from_raw, select_view, view_labels
from .manifest import MANIFEST_NAME, read_manifest, verify_models
from ..images import normalize_minmax

__all__ = [
    "RUNTIMES", "KIND_METADATA_KEY", "InitPredictor", "RefinePredictor", "ModelSet", "load_models", "torch_predictors",
    "onnx_predictors", "resolve_torch_device",
]

#: Network runtimes.
RUNTIMES = ("torch", "onnxruntime")
#: Key of the ONNX metadata entry that records the network kind (written by ``export_onnx``).
KIND_METADATA_KEY = "geopose_kind"


class InitPredictor(Protocol):
    def predict(
        self, image: np.ndarray, is_lateral: np.ndarray | bool | None = None, mirror: bool = True,
        view: np.ndarray | int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """image ``(B, 1, H, W)`` -> pose ``(B, 4, 4)``, view ``(B,)``, logits ``(B, 3)`` (see :class:`_Init`)."""
        ...


class RefinePredictor(Protocol):
    def predict_residual(self, target: np.ndarray, render: np.ndarray, view: np.ndarray | int) -> np.ndarray:
        """(target, render ``(B, 1, H, W)``, view) -> residual ``D`` ``(B, 4, 4)``; apply ``inverse(D) @ T``."""
        ...


def _images(name: str, image: np.ndarray, image_px: int | None) -> np.ndarray:
    """``image`` ``(B, 1, H, W)`` as the network takes it: block-averaged down to ``image_px`` square
    (the network's input size; None: any size), min-max normalised, float32."""
    image = np.asarray(image)
    if image.ndim != 4 or image.shape[1] != 1:
        raise ValueError(f"{name} must be a (B, 1, H, W) batch, got shape {image.shape}; "
                         "render or resample onto the model detector")
    if image_px is not None and image.shape[2:] != (image_px, image_px):
        factor = image.shape[2] // image_px
        if image.shape[2] != image.shape[3] or factor < 1 or image.shape[2] != factor * image_px:
            raise ValueError(f"{name} is {image.shape[2]} x {image.shape[3]} px but the network takes {image_px} x "
                             f"{image_px}: give square images of a whole multiple of that size")
        image = image.reshape(image.shape[0], 1, image_px, factor, image_px, factor).mean(axis=(3, 5))
    return normalize_minmax(image.astype(np.float32))


class _Init:
    """GeoPose-Init: the view rule and decoding around :meth:`_raw`, which runs the network.
    ``image_px``: the square input size the network takes; larger model-detector images are
    block-averaged to it (None: any size, e.g. a torch module outside a models folder)."""

    image_px: int | None = None

    def predict(
        self, image: np.ndarray, is_lateral: np.ndarray | bool | None = None, mirror: bool = True,
        view: np.ndarray | int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pose ``(B, 4, 4)``, view labels ``(B,)`` and view logits ``(B, 3)`` for a batch of images.

        ``is_lateral`` is the acquisition's PA/lateral metadata (None: the logits decide all
        three views); ``view`` fixes the labels instead (e.g. the side from the acquisition
        geometry; the logits are still returned). With ``mirror`` the logits are averaged with
        those of the column-mirrored images (:func:`~geopose.nets.decoding.mirror_averaged_logits`,
        one pass of 2B images): the lateral side is then decided more reliably than by the
        published single-image rule; poses are unaffected.
        """
        image = _images("image", image, self.image_px)
        batch = len(image)
        raw_all, logits = self._raw(np.concatenate((image, image[..., ::-1])) if mirror else image)
        if mirror:
            raw_all, logits = raw_all[:batch], mirror_averaged_logits(logits[:batch], logits[batch:])
        view = select_view(logits, is_lateral) if view is None else view_labels(view, batch)
        return decode_init_pose(raw_all[np.arange(batch), view], view), view, logits

    def _raw(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw pose for every view label ``(B, 3, 6)`` and view logits ``(B, 3)``."""
        raise NotImplementedError


class _Refine:
    """GeoPose-Refine: decoding around :meth:`_raw`, which runs the network (``image_px`` as for Init)."""

    image_px: int | None = None

    def predict_residual(self, target: np.ndarray, render: np.ndarray, view: np.ndarray | int) -> np.ndarray:
        """Residual ``D`` ``(B, 4, 4)`` for (target, current render) pairs; update ``T_new = inverse(D) @ T``."""
        target, render = _images("target", target, self.image_px), _images("render", render, self.image_px)
        if target.shape != render.shape:
            raise ValueError(f"target {target.shape} and render {render.shape} must be pairs of the same shape")
        return residual_from_raw(self._raw(target, render, view_labels(view, len(target))))

    def _raw(self, target: np.ndarray, render: np.ndarray, view: np.ndarray) -> np.ndarray:
        """Raw residual ``(B, 6)``."""
        raise NotImplementedError


# ------------------------------------------------------------------------ torch


def resolve_torch_device(device: str) -> "Any":
    """``auto`` takes CUDA when present; ``cuda`` without a GPU is a clear error."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"device {device!r} was asked for but no CUDA device is available: use device 'cpu' or 'auto'")
    return torch.device(device)


class TorchInit(_Init):
    """Init on a torch :class:`~geopose.nets.models.InitNet` (eval mode) on its device."""

    def __init__(self, module: Any, image_px: int | None = None) -> None:
        self.module = module.eval()
        self.device = next(module.parameters()).device
        self.image_px = image_px

    def _raw(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import torch

        with torch.no_grad():
            raw, logits = self.module.forward_all_views(torch.as_tensor(np.ascontiguousarray(image), device=self.device))
        return raw.double().cpu().numpy(), logits.double().cpu().numpy()


class TorchRefine(_Refine):
    """Refine on a torch :class:`~geopose.nets.models.RefineNet` (eval mode) on its device."""

    def __init__(self, module: Any, image_px: int | None = None) -> None:
        self.module = module.eval()
        self.device = next(module.parameters()).device
        self.image_px = image_px

    def _raw(self, target: np.ndarray, render: np.ndarray, view: np.ndarray) -> np.ndarray:
        import torch

        as_t = lambda a: torch.as_tensor(np.ascontiguousarray(a), device=self.device)  # noqa: E731
        with torch.no_grad():
            return self.module(as_t(target), as_t(render), as_t(view)).double().cpu().numpy()


def torch_predictors(init_module: Any, refine_module: Any, image_px: dict[str, int] | None = None) -> tuple[TorchInit, TorchRefine]:
    """Predictors of two torch modules (e.g. from training), checked for their kinds; ``image_px``:
    each network's input size by kind (default: any size)."""
    for kind, module in (("init", init_module), ("refine", refine_module)):
        if getattr(getattr(module, "config", None), "kind", None) != kind:
            raise ValueError(f"expected a GeoPose {kind} network, got {type(module).__name__}")
    sizes = image_px or {}
    return TorchInit(init_module, sizes.get("init")), TorchRefine(refine_module, sizes.get("refine"))


# ------------------------------------------------------------------ onnxruntime


class _Session:
    """An onnxruntime session of one GeoPose graph, checked for its kind and image size."""

    kind = ""

    def _open(self, model: bytes | str | os.PathLike, use_cuda: bool) -> None:
        import onnxruntime as ort

        providers = ["CPUExecutionProvider"]
        if use_cuda:
            if "CUDAExecutionProvider" in ort.get_available_providers():
                providers.insert(0, "CUDAExecutionProvider")
            else:
                warnings.warn("onnxruntime has no CUDA provider here; running on CPU (install onnxruntime-gpu for CUDA)")
        try:
            self.session = ort.InferenceSession(model if isinstance(model, bytes) else os.fspath(model), providers=providers)
        except Exception as exc:  # onnxruntime raises its own exception types for junk files
            raise InputError(f"the {self.kind} ONNX graph cannot be loaded ({str(exc).splitlines()[0][:200]}); "
                             "restore it from the GeoPose release or re-ship the models with `geopose train ship`") from None
        kind = self.session.get_modelmeta().custom_metadata_map.get(KIND_METADATA_KEY)
        if kind != self.kind:
            raise InputError(f"the ONNX graph given as GeoPose-{self.kind.title()} is "
                             f"{'a GeoPose-' + kind.title() + ' network' if kind else 'not a GeoPose graph'}; "
                             "export it with geopose.nets.export_onnx")
        self.image_px = int(self.session.get_inputs()[0].shape[-1])


class OnnxInit(_Init, _Session):
    """Init on an onnxruntime session (a graph from :func:`~geopose.nets.onnx_export.export_onnx`)."""

    kind = "init"

    def __init__(self, model: bytes | str | os.PathLike, use_cuda: bool = False) -> None:
        self._open(model, use_cuda)

    def _raw(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raw, logits = self.session.run(None, {"image": np.ascontiguousarray(image)})
        return raw.astype(np.float64), logits.astype(np.float64)


class OnnxRefine(_Refine, _Session):
    """Refine on an onnxruntime session."""

    kind = "refine"

    def __init__(self, model: bytes | str | os.PathLike, use_cuda: bool = False) -> None:
        self._open(model, use_cuda)

    def _raw(self, target: np.ndarray, render: np.ndarray, view: np.ndarray) -> np.ndarray:
        (raw,) = self.session.run(None, {"target": target, "render": render, "view": view.astype(np.int64)})
        return raw.astype(np.float64)


def onnx_predictors(graphs: dict[str, bytes | str | os.PathLike], use_cuda: bool = False) -> tuple[OnnxInit, OnnxRefine]:
    """Predictors of ``{"init": graph, "refine": graph}`` (paths or bytes)."""
    if set(graphs) != {"init", "refine"}:
        raise InputError(f"ONNX graphs must be given for both 'init' and 'refine', got {sorted(graphs)}")
    return OnnxInit(graphs["init"], use_cuda), OnnxRefine(graphs["refine"], use_cuda)


# ------------------------------------------------------------------- model sets


@dataclass
class ModelSet:
    """Init and Refine as the pipeline runs them, with what the networks expect.

    ``render_px``: pixels per side of the DRRs the networks were trained on (rendered
    on the 256-px model detector's field of view, then resized to it);
    ``clip_percentiles``: the MAP clip of their input images; ``files``: per network
    kind, the file used and its SHA-256; ``runtime``: ``torch`` or ``onnxruntime``."""

    init: InitPredictor
    refine: RefinePredictor
    render_px: int = C.MODEL_DETECTOR_PX
    clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES
    runtime: str = "torch"
    device: str = "cpu"
    files: dict[str, dict] = field(default_factory=dict)

    def describe(self) -> dict:
        """What the result record says about the models."""
        return {"runtime": self.runtime, "device": self.device, "render_px": self.render_px,
                "clip_percentiles": list(self.clip_percentiles), **self.files}


@dataclass(frozen=True)
class ModelInput:
    """What one network takes, as its manifest entry (or model file) declares: ``render_px``, the
    pixels its DRRs are rendered at on the model detector's field of view; ``clip_percentiles``, the
    MAP clip; ``image_px``, its own input size (the 256-px model images are block-averaged to it)."""

    render_px: int = C.MODEL_DETECTOR_PX
    clip_percentiles: tuple[float, float] = C.MAP_CLIP_PERCENTILES
    image_px: int = C.MODEL_DETECTOR_PX


def _model_input(entry: dict) -> ModelInput:
    """The :class:`ModelInput` a manifest entry or model-file metadata declares; older entries: the
    training config, else the model detector size and docs/conventions.md 5."""
    inputs = entry.get("input", {}) if isinstance(entry.get("input"), dict) else {}
    config = entry.get("training", {}).get("config", {}) if isinstance(entry.get("training"), dict) else {}
    render_px = int(inputs.get("render_px", config.get("render_px", C.MODEL_DETECTOR_PX)))
    clip = inputs.get("clip_percentiles", C.MAP_CLIP_PERCENTILES)
    image_px = int(inputs.get("image_px", config.get("image_px", C.MODEL_DETECTOR_PX)))
    if image_px < 1 or C.MODEL_DETECTOR_PX % image_px:
        raise InputError(f"a network declares an input of {image_px} px, which the {C.MODEL_DETECTOR_PX}-px model detector "
                         "cannot be block-averaged to: re-ship the model with a divisor of that size")
    return ModelInput(render_px, (float(clip[0]), float(clip[1])), image_px)


def load_models(
    models: str | os.PathLike | None = None, *, runtime: str = "torch", device: str = "cpu", allow_unverified: bool = False
) -> ModelSet:
    """The networks of a models folder (default: the shipped models), every file checked against
    ``manifest.json`` (size and SHA-256) before use (:func:`~geopose.nets.manifest.verify_models`;
    ``allow_unverified``: a folder without a manifest, its ``.pt`` files unchecked). ``runtime``
    ``torch`` runs the ``.pt`` model files on ``device``; ``onnxruntime`` runs the ONNX graphs the
    manifest lists (CUDA provider when ``device`` is CUDA and onnxruntime-gpu is installed; an
    unverified folder's ``.pt`` files are exported in memory)."""
    if runtime not in RUNTIMES:
        raise InputError(f"network runtime must be one of {RUNTIMES}, got {runtime!r}")
    folder = Path(models) if models is not None else default_models_dir()
    listed = (folder / MANIFEST_NAME).is_file()
    fmt = "onnx" if runtime == "onnxruntime" and listed else "pt"
    paths = verify_models(folder, fmt, allow_unverified=allow_unverified)
    if listed:
        manifest = read_manifest(folder)["models"]
        entries = {k: manifest[k] if fmt == "pt" else manifest[k]["onnx"] for k in paths}
        files = {k: {"path": str(p), "sha256": entries[k]["sha256"], "format": fmt} for k, p in paths.items()}
        inputs = {k: _model_input(manifest[k]) for k in ("init", "refine")}
    else:
        from .model_io import read_model_header

        files = {k: {"path": str(p), "sha256": "unverified (no manifest)", "format": fmt} for k, p in paths.items()}
        inputs = {k: _model_input(read_model_header(p).get("metadata", {})) for k, p in paths.items()}
    shared = {k: (v.render_px, v.clip_percentiles) for k, v in inputs.items()}
    if shared["init"] != shared["refine"]:
        raise InputError(f"{folder}: Init and Refine declare different DRR sizes or MAP clips ({shared}); ship a matching pair")
    sizes = {k: v.image_px for k, v in inputs.items()}
    for k in files:
        files[k]["image_px"] = sizes[k]
    if runtime == "torch" or fmt == "pt":
        from .model_io import load_model

        dev = resolve_torch_device(device) if runtime == "torch" else resolve_torch_device("cpu")
        modules = {k: load_model(paths[k], dev) for k in ("init", "refine")}
        if runtime == "torch":
            init, refine = torch_predictors(modules["init"], modules["refine"], sizes)
            device = str(dev)
        else:
            from .onnx_export import export_onnx

            init, refine = onnx_predictors({k: export_onnx(m, image_px=sizes[k]) for k, m in modules.items()},
                                           use_cuda=device.startswith("cuda"))
    else:
        init, refine = onnx_predictors(paths, use_cuda=device.startswith("cuda"))
    if runtime == "onnxruntime":
        device = "cuda" if device.startswith("cuda") else "cpu"
    return ModelSet(init, refine, inputs["init"].render_px, inputs["init"].clip_percentiles, runtime, device, files)
