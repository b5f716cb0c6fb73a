"""Where the shipped resources (models, icons) live: next to the library in the
source tree and in the built Slicer extension, or where ``GEOPOSE_RESOURCES`` points."""

from __future__ import annotations

import os
from pathlib import Path
from .errors import InputError

__all__ = ["resources_dir", "default_models_dir"]


def resources_dir() -> Path:
    """The ``Resources`` folder: ``$GEOPOSE_RESOURCES``, else ``Logic/../Resources`` of the source tree."""
    env = os.environ.get("GEOPOSE_RESOURCES")
    candidates = [Path(env)] if env else []
    here = Path(__file__).resolve().parent
    candidates += [here.parents[1] / "Resources", here / "Resources"]
    for c in candidates:
        if c.is_dir():
            return c
    raise InputError(
        "GeoPose resources not found (looked in " + ", ".join(str(c) for c in candidates) + "): "
        "set GEOPOSE_RESOURCES to the extension's Resources folder"
    )


def default_models_dir() -> Path:
    return resources_dir() / "Models"
