"""Reading ``Resources/Models/manifest.json`` and checking the files it lists (no PyTorch).

Per network kind the manifest names the torch model file (``file``, ``sha256``,
``bytes``) and, under ``onnx``, the same network as an ONNX graph. Every entry is
validated (an object with a file name inside the models folder, a byte count, a
SHA-256) and every file checked (existence, size, SHA-256) before use.
:func:`verify_models` is the one gate for a models folder: without a manifest it is
refused unless the caller explicitly allows unverified models.
``geopose.training.manifest`` writes the manifest.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..checksums import file_sha256
from ..errors import InputError
from ..jsonio import read_json

__all__ = [
    "MANIFEST_NAME", "MANIFEST_SCHEMA", "MODEL_FORMATS", "MODEL_KINDS_NEEDED",
    "lists_format", "read_manifest", "verify_manifest", "verify_models",
]

MANIFEST_NAME = "manifest.json"
MANIFEST_SCHEMA = 1
#: ``pt``: GeoPose model files for torch; ``onnx``: graphs for onnxruntime.
MODEL_FORMATS = ("pt", "onnx")
#: The networks a registration needs.
MODEL_KINDS_NEEDED = ("init", "refine")
_SHA256 = re.compile(r"[0-9a-f]{64}")
_RESTORE = "restore the models folder from the GeoPose release (or re-ship it with `geopose train ship`)"


def read_manifest(models_dir: str | os.PathLike) -> dict:
    """The parsed manifest of ``models_dir``; errors name the file and the remedy."""
    path = Path(models_dir) / MANIFEST_NAME
    if not path.is_file():
        raise InputError(f"{path} does not exist; {_RESTORE}")
    manifest = read_json(path, _RESTORE)
    if not isinstance(manifest, dict) or manifest.get("schema_version") != MANIFEST_SCHEMA or not isinstance(manifest.get("models"), dict):
        raise InputError(f"{path} is not a schema-{MANIFEST_SCHEMA} GeoPose model manifest; {_RESTORE}")
    return manifest


def _file_entry(models_dir: Path, kind: str, entry: object, what: str) -> tuple[Path, int, str]:
    """(path, bytes, sha256) of one manifest entry, validated and confined to ``models_dir``."""
    where = f"{models_dir / MANIFEST_NAME}: the {kind} {what} entry"
    if not isinstance(entry, dict):
        raise InputError(f"{where} must be an object with 'file', 'bytes' and 'sha256', got {type(entry).__name__}; {_RESTORE}")
    file, size, digest = entry.get("file"), entry.get("bytes"), entry.get("sha256")
    if not isinstance(file, str) or not file or not isinstance(size, int) or isinstance(size, bool) or size < 0:
        raise InputError(f"{where} needs a 'file' name and a whole-number 'bytes' (got file={file!r}, bytes={size!r}); {_RESTORE}")
    if not isinstance(digest, str) or not _SHA256.fullmatch(digest):
        raise InputError(f"{where} needs a 64-hex-digit 'sha256' (got {str(digest)[:70]!r}); {_RESTORE}")
    root = models_dir.resolve()
    path = (models_dir / file).resolve()
    if Path(file).is_absolute() or path.parent != root:
        raise InputError(f"{where} names {file!r}, which is not a file in the models folder {models_dir}; a manifest may only "
                         f"list files beside it; {_RESTORE}")
    return path, size, digest


def verify_manifest(models_dir: str | os.PathLike, fmt: str = "pt") -> dict[str, Path]:
    """Check every ``fmt`` model file listed in ``models_dir/manifest.json`` (entry, confinement,
    existence, size, SHA-256). Returns kind -> path; raises :class:`InputError` naming the file and the remedy."""
    if fmt not in MODEL_FORMATS:
        raise InputError(f"model format must be one of {MODEL_FORMATS}, got {fmt!r}")
    models_dir = Path(models_dir)
    found = {}
    for kind, entry in read_manifest(models_dir)["models"].items():
        if fmt == "onnx":
            if not isinstance(entry, dict) or "onnx" not in entry:
                raise InputError(
                    f"{models_dir / MANIFEST_NAME} lists no ONNX file for the {kind} network; "
                    "re-ship the models with `geopose train ship` (it exports them) or use the torch backend"
                )
            entry = entry["onnx"]
        file, size, digest = _file_entry(models_dir, kind, entry, "ONNX" if fmt == "onnx" else "model")
        if not file.is_file():
            raise InputError(f"model file {file} listed in {MANIFEST_NAME} is missing; {_RESTORE}")
        if file.stat().st_size != size or file_sha256(file) != digest:
            raise InputError(f"{file} does not match its size/SHA-256 in {MANIFEST_NAME} (corrupted or replaced); {_RESTORE}")
        found[kind] = file
    return found


def verify_models(models_dir: str | os.PathLike, fmt: str = "pt", *, allow_unverified: bool = False) -> dict[str, Path]:
    """The Init and Refine files (kind -> path) of a models folder, every one checked against the
    folder's manifest. A folder without a manifest is refused unless ``allow_unverified`` (CLI:
    ``--allow-unverified-models``): then its ``*.pt`` files are found by their headers (``fmt="pt"``
    only) and used unchecked."""
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise InputError(f"models folder {models_dir} does not exist; pass the folder holding {MANIFEST_NAME} and the model files")
    if not (models_dir / MANIFEST_NAME).is_file():
        if not allow_unverified:
            raise InputError(
                f"{models_dir} has no {MANIFEST_NAME}, so its model files cannot be verified: use a shipped models folder, "
                "write a manifest with `geopose train ship`, or pass --allow-unverified-models (library: "
                "allow_unverified=True) to use them unchecked"
            )
        if fmt != "pt":
            raise InputError(f"{models_dir} has no {MANIFEST_NAME}: unverified models are read as .pt files only; use fmt='pt'")
        from .model_io import find_model_files  # torch is needed only here

        return find_model_files(models_dir)
    found = verify_manifest(models_dir, fmt)
    missing = [kind for kind in MODEL_KINDS_NEEDED if kind not in found]
    if missing:
        raise InputError(f"{models_dir / MANIFEST_NAME} lists no {' or '.join(missing)} model; {_RESTORE}")
    return {kind: found[kind] for kind in MODEL_KINDS_NEEDED}


def lists_format(models_dir: str | os.PathLike, fmt: str) -> bool:
    """Whether ``models_dir`` has a manifest listing a ``fmt`` file for every network."""
    if not (Path(models_dir) / MANIFEST_NAME).is_file():
        return False
    models = read_manifest(models_dir)["models"]
    return bool(models) and all(fmt == "pt" or (isinstance(entry, dict) and fmt in entry) for entry in models.values())
