"""Reading ``Resources/Models/manifest.json`` and checking the files it lists (no PyTorch).

Per network kind the manifest names the torch model file (``file``, ``sha256``,
``bytes``) and, under ``onnx``, the same network as an ONNX graph. Every file is
checked (existence, size, SHA-256) before use. ``geopose.training.manifest`` writes it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..checksums import file_sha256

__all__ = ["MANIFEST_NAME", "MANIFEST_SCHEMA", "MODEL_FORMATS", "lists_format", "read_manifest", "verify_manifest"]

MANIFEST_NAME = "manifest.json"
MANIFEST_SCHEMA = 1
#: ``pt``: GeoPose model files for torch; ``onnx``: graphs for onnxruntime.
MODEL_FORMATS = ("pt", "onnx")


def read_manifest(models_dir: str | os.PathLike) -> dict:
    """The parsed manifest of ``models_dir``; errors name the file and the remedy."""
    path = Path(models_dir) / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist; ship models with `geopose train ship` or reinstall GeoPose")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); restore it from the GeoPose release") from None
    if manifest.get("schema_version") != MANIFEST_SCHEMA or not isinstance(manifest.get("models"), dict):
        raise ValueError(f"{path} is not a schema-{MANIFEST_SCHEMA} GeoPose model manifest; restore it from the release")
    return manifest


def verify_manifest(models_dir: str | os.PathLike, fmt: str = "pt") -> dict[str, Path]:
    """Check every ``fmt`` model file listed in ``models_dir/manifest.json`` (existence, size, SHA-256).

    Returns kind -> path. Raises FileNotFoundError / ValueError naming the file and the remedy.
    """
    if fmt not in MODEL_FORMATS:
        raise ValueError(f"model format must be one of {MODEL_FORMATS}, got {fmt!r}")
    models_dir = Path(models_dir)
    found = {}
    for kind, entry in read_manifest(models_dir)["models"].items():
        if fmt == "onnx":
            if "onnx" not in entry:
                raise FileNotFoundError(
                    f"{models_dir / MANIFEST_NAME} lists no ONNX file for the {kind} network; "
                    "re-ship the models with `geopose train ship` (it exports them) or use the torch backend"
                )
            entry = entry["onnx"]
        file = models_dir / entry["file"]
        if not file.is_file():
            raise FileNotFoundError(f"model file {file} listed in {MANIFEST_NAME} is missing; restore it from the release")
        if file.stat().st_size != entry["bytes"] or file_sha256(file) != entry["sha256"]:
            raise ValueError(f"{file} does not match its SHA-256 in {MANIFEST_NAME} (corrupted or replaced); restore it from the release")
        found[kind] = file
    return found


def lists_format(models_dir: str | os.PathLike, fmt: str) -> bool:
    """Whether ``models_dir`` has a manifest listing a ``fmt`` file for every network."""
    if not (Path(models_dir) / MANIFEST_NAME).is_file():
        return False
    models = read_manifest(models_dir)["models"]
    return bool(models) and all(fmt == "pt" or fmt in entry for entry in models.values())
