"""Where the project's ``shared/`` folder (third-party test data, Slicer's Python layer, reference
files) is, for the tests and for the scripts they run in subprocesses (standard library only)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def find_shared() -> Path:
    """``$GEOPOSE_SHARED``, else ``shared/`` beside the repository, else beside the repository this
    one was cloned from (a clone in a temporary folder); the first candidate when none exists."""
    if os.environ.get("GEOPOSE_SHARED"):
        return Path(os.environ["GEOPOSE_SHARED"])
    candidates = [REPO.parent / "shared"]
    try:
        origin = subprocess.run(["git", "-C", str(REPO), "config", "--get", "remote.origin.url"],
                                capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        origin = ""
    if origin and "://" not in origin and Path(origin).is_dir():
        candidates.append(Path(origin).resolve().parent / "shared")
    return next((c for c in candidates if c.is_dir()), candidates[0])
