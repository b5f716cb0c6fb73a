"""``Resources/Models/manifest.json``: what the shipped model files are, and their checksums.

The manifest lists, per network kind, the file name, its SHA-256 and size (and the
same for the network's ONNX graph under ``onnx``), the
architecture, the input geometry, the training recipe and seeds, and the
validation metrics. :func:`geopose.nets.manifest.verify_manifest` checks every listed file before use.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..contract import MAP_CLIP_PERCENTILES, MODEL_DETECTOR_PX, MODEL_PIXEL_SPACING_MM, MODEL_SDD_MM
from ..nets import read_model_header
from ..checksums import file_sha256
from ..nets.manifest import MANIFEST_NAME, MANIFEST_SCHEMA, verify_manifest

__all__ = ["MANIFEST_NAME", "MANIFEST_SCHEMA", "file_entry", "file_sha256", "model_entry", "verify_manifest", "write_manifest"]


def file_entry(path: str | os.PathLike) -> dict:
    """``{"file", "sha256", "bytes"}`` of one file in the models folder."""
    path = Path(path)
    return {"file": path.name, "sha256": file_sha256(path), "bytes": path.stat().st_size}


def model_entry(path: str | os.PathLike, **extra) -> dict:
    """Manifest entry of one model file: name, checksum, size, architecture, input geometry + ``extra``."""
    path = Path(path)
    header = read_model_header(path)
    config = header.get("metadata", {}).get("training", {}).get("config", {})
    return {
        **file_entry(path),
        "architecture": header["architecture"],
        "storage_dtype": header["storage_dtype"],
        "input": {
            "image_px": int(config.get("image_px", MODEL_DETECTOR_PX)),
            "pixel_spacing_mm": MODEL_PIXEL_SPACING_MM,
            "sdd_mm": MODEL_SDD_MM,
            "channels": 1,
            "pairing": header["architecture"].get("pairing", "siamese"),
            "normalisation": "per-image min-max to [0, 1]",
            "render_px": int(config.get("render_px", MODEL_DETECTOR_PX)),
            "clip_percentiles": list(config.get("input_clip", MAP_CLIP_PERCENTILES)),
        },
        **extra,
    }


def write_manifest(models_dir: str | os.PathLike, entries: dict[str, dict], notes: dict | None = None) -> Path:
    """Write ``manifest.json`` with ``entries`` (kind -> :func:`model_entry`) and free-form ``notes``."""
    path = Path(models_dir) / MANIFEST_NAME
    payload = {"schema_version": MANIFEST_SCHEMA, "models": entries, **(notes or {})}
    path.write_text(json.dumps(payload, indent=2, sort_keys=True) + "\n")
    return path
