"""``Resources/Models/manifest.json``: what the shipped model files are, and their checksums.

The manifest lists, per network kind, the file name, its SHA-256 and size, the
architecture, the input geometry, the training recipe and seeds, and the
validation metrics. :func:`verify_manifest` checks every listed file before use.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from ..contract import MODEL_DETECTOR_PX, MODEL_PIXEL_SPACING_MM, MODEL_SDD_MM
from ..nets import read_model_header

MANIFEST_NAME = "manifest.json"
MANIFEST_SCHEMA = 1
_CHUNK = 1 << 20


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(_CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def model_entry(path: str | os.PathLike, **extra) -> dict:
    """Manifest entry of one model file: name, checksum, size, architecture, input geometry + ``extra``."""
    path = Path(path)
    header = read_model_header(path)
    return {
        "file": path.name,
        "sha256": file_sha256(path),
        "bytes": path.stat().st_size,
        "architecture": header["architecture"],
        "storage_dtype": header["storage_dtype"],
        "input": {
            "image_px": MODEL_DETECTOR_PX,
            "pixel_spacing_mm": MODEL_PIXEL_SPACING_MM,
            "sdd_mm": MODEL_SDD_MM,
            "channels": 1,
            "normalisation": "per-image min-max to [0, 1]",
        },
        **extra,
    }


def write_manifest(models_dir: str | os.PathLike, entries: dict[str, dict], notes: dict | None = None) -> Path:
    """Write ``manifest.json`` with ``entries`` (kind -> :func:`model_entry`) and free-form ``notes``."""
    path = Path(models_dir) / MANIFEST_NAME
    payload = {"schema_version": MANIFEST_SCHEMA, "models": entries, **(notes or {})}
    path.write_text(json.dumps(payload, indent=2, sort_keys=True) + "\n")
    return path


def verify_manifest(models_dir: str | os.PathLike) -> dict[str, Path]:
    """Check every model file listed in ``models_dir/manifest.json`` (existence, size, SHA-256).

    Returns kind -> path. Raises FileNotFoundError / ValueError naming the file and the remedy.
    """
    models_dir = Path(models_dir)
    path = models_dir / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist; ship models with `geopose train ship` or reinstall GeoPose")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); restore it from the GeoPose release") from None
    if manifest.get("schema_version") != MANIFEST_SCHEMA or not isinstance(manifest.get("models"), dict):
        raise ValueError(f"{path} is not a schema-{MANIFEST_SCHEMA} GeoPose model manifest; restore it from the release")
    found = {}
    for kind, entry in manifest["models"].items():
        file = models_dir / entry["file"]
        if not file.is_file():
            raise FileNotFoundError(f"model file {file} listed in {path.name} is missing; restore it from the release")
        if file.stat().st_size != entry["bytes"] or file_sha256(file) != entry["sha256"]:
            raise ValueError(f"{file} does not match its SHA-256 in {path.name} (corrupted or replaced); restore it from the release")
        found[kind] = file
    return found
