"""GeoPose model files: one ``.pt`` file = a JSON header + a plain dict of tensors.

The file is written with ``torch.save`` of ``{"header": <JSON text>, "state_dict":
{name: tensor}}`` and read with ``torch.load(weights_only=True)``, so loading never
executes pickled code. The header names the format, the architecture
(:class:`NetConfig`), the stored dtype and free-form metadata.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from ..errors import InputError
from .models import InitNet, NetConfig, RefineNet, build_model

MODEL_FORMAT = "geopose-model"
MODEL_FORMAT_VERSION = 1
MODEL_SUFFIX = ".pt"
#: Storage dtypes a model file may use for its floating-point tensors.
STORAGE_DTYPES = {"float32": torch.float32, "float16": torch.float16}


def save_model(
    module: InitNet | RefineNet,
    path: str | os.PathLike,
    metadata: dict[str, Any] | None = None,
    *,
    dtype: str = "float32",
) -> Path:
    """Write ``module`` to ``path`` (a ``.pt`` file); floating tensors stored as ``dtype``.

    ``metadata`` must be JSON-serialisable (e.g. provenance, training data, metrics).
    """
    if not isinstance(module, (InitNet, RefineNet)):
        raise TypeError(f"save_model takes an InitNet or RefineNet, got {type(module).__name__}")
    if dtype not in STORAGE_DTYPES:
        raise ValueError(f"storage dtype must be one of {sorted(STORAGE_DTYPES)}, got {dtype!r}")
    header = {
        "format": MODEL_FORMAT,
        "format_version": MODEL_FORMAT_VERSION,
        "architecture": module.config.to_dict(),
        "storage_dtype": dtype,
        "metadata": metadata or {},
    }
    try:
        header_text = json.dumps(header, sort_keys=True)
    except TypeError as exc:
        raise ValueError(f"model metadata must be JSON-serialisable: {exc}") from exc
    state = {
        name: (t.detach().to("cpu", STORAGE_DTYPES[dtype]) if t.is_floating_point() else t.detach().cpu()).contiguous()
        for name, t in module.state_dict().items()
    }
    overflow = [name for name, t in state.items() if t.is_floating_point() and not torch.isfinite(t).all()]
    if overflow:
        raise ValueError(f"weights {overflow[:3]} are not finite when stored as {dtype}; store as float32")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"header": header_text, "state_dict": state}, path)
    return path


def _read(path: str | os.PathLike) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"model file {path} does not exist; import or train a model first")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign files
        raise InputError(
            f"{path} is not a GeoPose model file ({type(exc).__name__}); "
            "published Lightning checkpoints must first go through `geopose import-checkpoint`"
        ) from None
    header = None
    if isinstance(payload, dict) and isinstance(payload.get("header"), str):
        try:
            header = json.loads(payload["header"])
        except json.JSONDecodeError:
            header = None
    if not isinstance(header, dict) or header.get("format") != MODEL_FORMAT or not isinstance(payload.get("state_dict"), dict):
        raise InputError(
            f"{path} is not a GeoPose model file (no '{MODEL_FORMAT}' header); "
            "published Lightning checkpoints must first go through `geopose import-checkpoint`"
        )
    if header.get("format_version") != MODEL_FORMAT_VERSION:
        raise InputError(
            f"{path} has model format version {header.get('format_version')}, this library reads "
            f"version {MODEL_FORMAT_VERSION}; update GeoPose or re-export the model"
        )
    return header, payload["state_dict"]


def read_model_header(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON header of a model file (format, architecture, storage dtype, metadata)."""
    return _read(path)[0]


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu") -> InitNet | RefineNet:
    """Rebuild the module described by a model file, load its weights strictly (float32), eval mode."""
    header, state = _read(path)
    try:
        module = build_model(NetConfig.from_dict(header["architecture"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path} has an unreadable architecture in its header ({exc}); re-export or re-import the model") from None
    state = {name: (t.float() if t.is_floating_point() else t) for name, t in state.items()}
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise InputError(f"{path}: weights do not match the architecture in its header: {' '.join(str(exc).split())[:300]}") from None
    return module.to(device).eval()


def find_model_files(directory: str | os.PathLike) -> dict[str, Path]:
    """The Init and Refine model files of a directory, keyed ``"init"``/``"refine"`` by their headers."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"model directory {directory} does not exist")
    found: dict[str, Path] = {}
    for candidate in sorted(directory.glob(f"*{MODEL_SUFFIX}")):
        architecture = read_model_header(candidate).get("architecture")
        kind = architecture.get("kind") if isinstance(architecture, dict) else None
        if kind not in ("init", "refine"):
            raise InputError(f"{candidate} names no init/refine network in its header; remove it or re-export it")
        if kind in found:
            raise InputError(f"{directory} holds two {kind} models ({found[kind].name}, {candidate.name}); keep one")
        found[kind] = candidate
    missing = [kind for kind in ("init", "refine") if kind not in found]
    if missing:
        raise InputError(
            f"{directory} has no {' or '.join(missing)} model file (*{MODEL_SUFFIX}); "
            "import the published checkpoints with `geopose import-checkpoint` or train one"
        )
    return found

