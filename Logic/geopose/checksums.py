"""SHA-256 of input files and shipped models (one implementation for the library)."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable

__all__ = ["file_sha256"]

_CHUNK_BYTES = 1 << 20


def file_sha256(paths: str | os.PathLike | Iterable[str | os.PathLike]) -> str:
    """Hex SHA-256 of one file, or of several files' bytes concatenated in the given order."""
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    digest = hashlib.sha256()
    for path in items:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(_CHUNK_BYTES), b""):
                digest.update(block)
    return digest.hexdigest()
