"""Shared pytest set-up: markers for slow and GPU-only tests, paths to shared data."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


def _find_shared() -> Path:
    """The project's ``shared/`` folder (third-party test data, reference files): ``$GEOPOSE_SHARED``,
    else beside the repository, else beside the repository this one was cloned from (CI clones
    the checkout into a temporary folder)."""
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


SHARED = _find_shared()
SHARED_DATA = SHARED / "data"


def pytest_collection_modifyitems(config, items):
    run_slow = os.environ.get("GEOPOSE_SLOW") == "1"
    has_cuda = torch.cuda.is_available()
    for item in items:
        if "slow" in item.keywords and not run_slow:
            item.add_marker(pytest.mark.skip(reason="slow test: set GEOPOSE_SLOW=1 (or `make test-slow`)"))
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(pytest.mark.skip(reason="needs a CUDA device"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA
