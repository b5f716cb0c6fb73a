"""Installing GeoPose's Python requirements into Slicer's Python without changing a package Slicer ships.

Standard library only, Python 3.9 or later (Slicer 5.8), so that it runs in any Slicer and in the
test environments without Slicer. The rule: every distribution installed in the running
interpreter is pinned at its installed version (:func:`pip_constraints`, pip's ``-c``), so pip
picks versions of the new packages that fit those (e.g. on Slicer 5.8, whose numpy is 1.26.4, a
``pylibjpeg-libjpeg`` that does not need numpy 2) or installs nothing and says why; a requirement
whose package is installed but older than its floor is refused before pip runs
(:func:`shipped_too_old`), since meeting it would upgrade a package Slicer's own modules use.
"""

import importlib.metadata
import json
import re
import subprocess
import tempfile
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple


class DependencyError(RuntimeError):
    """The requirements cannot be installed here without changing an installed package (one line)."""


def normalized(name: str) -> str:
    """A distribution name as pip compares them (PEP 503): ``Pillow`` -> ``pillow``, ``pylibjpeg_rle`` -> ``pylibjpeg-rle``."""
    return re.sub(r"[-_.]+", "-", name).lower()


def release(version: str) -> Tuple[int, ...]:
    """The numeric release of a version string: ``"2.4.4"`` -> (2, 4, 4), ``"2.13.0+cu126"`` -> (2, 13, 0)."""
    return tuple(int(p) for p in re.match(r"\d+(\.\d+)*", version).group(0).split("."))


def split_requirement(requirement: str) -> Tuple[str, str]:
    """``"name>=floor"`` -> ``(name, floor)``; the only form GeoPose's requirements take."""
    name, floor = requirement.split(">=")
    return name.strip(), floor.strip()


def installed_versions() -> Dict[str, str]:
    """``{normalized name: version}`` of every distribution the running interpreter sees."""
    found: Dict[str, str] = {}
    for dist in importlib.metadata.distributions():
        name, version = dist.metadata["Name"], dist.version
        if name and version:
            found.setdefault(normalized(name), version)  # the first on sys.path is the one imported
    return found


def _installed_version(name: str, installed: Optional[Dict[str, str]]) -> Optional[str]:
    """The installed version of distribution ``name`` (from ``installed``, else looked up), or None."""
    if installed is not None:
        return installed.get(normalized(name))
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def unmet(requirements: Iterable[str], installed: Optional[Dict[str, str]] = None) -> List[str]:
    """The requirements not installed at their floor version or newer (``installed``: as
    :func:`installed_versions` gives it; looked up per requirement when None)."""
    missing = []
    for requirement in requirements:
        name, floor = split_requirement(requirement)
        version = _installed_version(name, installed)
        if version is None or release(version) < release(floor):
            missing.append(requirement)
    return missing


def shipped_too_old(requirements: Iterable[str], installed: Optional[Dict[str, str]] = None) -> List[Tuple[str, str]]:
    """``(requirement, installed version)`` for each requirement whose package is installed below its floor:
    meeting it would replace a package of Slicer's own Python, which GeoPose never does."""
    found = []
    for requirement in unmet(requirements, installed):
        version = _installed_version(split_requirement(requirement)[0], installed)
        if version is not None:
            found.append((requirement, version))
    return found


def pip_constraints(installed: Optional[Dict[str, str]] = None) -> str:
    """pip constraints pinning every installed distribution at its version (``name==version`` lines)."""
    installed = installed_versions() if installed is None else installed
    return "".join(f"{name}=={version}\n" for name, version in sorted(installed.items()))


def write_constraints(folder: Path, installed: Optional[Dict[str, str]] = None) -> Path:
    """:func:`pip_constraints` written to ``folder/constraints.txt``."""
    path = Path(folder) / "constraints.txt"
    path.write_text(pip_constraints(installed))
    return path


def _pip_error(stderr: str) -> str:
    """The first ``ERROR:`` line pip printed (its reason), else its last line."""
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("ERROR:")]
    return (errors or lines or ["pip gave no reason"])[0]


def plan_install(python: str, requirements: Sequence[str], constraints: Optional[Path]) -> List[Tuple[str, str]]:
    """``[(name, version)]`` that ``python -m pip install -c constraints requirements`` would install
    (``pip install --dry-run --report``: resolved, nothing changed). Raises :class:`DependencyError` when
    pip finds no versions that fit."""
    with tempfile.TemporaryDirectory(prefix="geopose-pip-") as tmp:
        report = Path(tmp) / "report.json"
        args = [python, "-m", "pip", "install", "--dry-run", "--quiet", "--report", str(report)]
        args += ["-c", str(constraints)] if constraints is not None else []
        run = subprocess.run([*args, *requirements], capture_output=True, text=True)
        if run.returncode != 0:
            raise DependencyError(
                f"pip finds no versions of {', '.join(requirements)} that fit the packages of this Slicer "
                f"({_pip_error(run.stderr)}); nothing was installed"
            )
        install = json.loads(report.read_text()).get("install", [])
    return [(item["metadata"]["name"], item["metadata"]["version"]) for item in install]
