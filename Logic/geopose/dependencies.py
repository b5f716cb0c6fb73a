"""GeoPose's Python requirements, and installing them into 3D Slicer's Python without changing a
package Slicer ships.

The requirements are stated once, in ``requirements/*.txt`` beside this file: ``pyproject.toml``
reads them (its dependencies and extras), :data:`SLICER_REQUIREMENTS` and :data:`TORCH_REQUIREMENT`
are read from them here, and the Slicer module installs and checks those.

Standard library only, Python 3.9 or later (Slicer 5.8): the Slicer module imports this before
anything is installed. The install rule: every distribution installed in the running interpreter
is pinned at its installed version (:func:`pip_constraints`, pip's ``-c``), so pip picks versions
of the new packages that fit those (e.g. on Slicer 5.8, whose numpy is 1.26.4, a
``pylibjpeg-libjpeg`` that does not need numpy 2) or installs nothing and says why; a requirement
whose package is installed but older than its floor is refused before pip runs
(:func:`check_installable`), since meeting it would upgrade a package Slicer's own modules use.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

from .errors import InputError

__all__ = [
    "REQUIREMENTS_FOLDER", "SLICER_REQUIREMENTS", "TORCH_REQUIREMENT", "TORCH_MINIMUM_PYTHON", "TTO_BENEFIT",
    "DependencyError", "read_requirements", "missing", "torch_available", "torch_supported", "check_installable",
    "planned_install", "install_missing", "normalized", "release", "split_requirement", "installed_versions", "unmet",
    "shipped_too_old", "pip_constraints", "write_constraints", "plan_install",
]

#: The requirement files (``pyproject.toml`` reads them too).
REQUIREMENTS_FOLDER = Path(__file__).resolve().parent / "requirements"


class DependencyError(InputError):
    """The requirements cannot be installed here without changing an installed package (one line)."""


def read_requirements(name: str) -> Tuple[str, ...]:
    """The requirements of ``requirements/<name>.txt`` as setuptools reads them: one a line, whole-line
    ``#`` comments and blank lines skipped (``"torch>=2.13; python_version >= '3.10'"`` keeps its marker)."""
    lines = (line.strip() for line in (REQUIREMENTS_FOLDER / f"{name}.txt").read_text().splitlines())
    return tuple(line for line in lines if line and not line.startswith("#"))


def normalized(name: str) -> str:
    """A distribution name as pip compares them (PEP 503): ``Pillow`` -> ``pillow``, ``pylibjpeg_rle`` -> ``pylibjpeg-rle``."""
    return re.sub(r"[-_.]+", "-", name).lower()


def release(version: str) -> Tuple[int, ...]:
    """The numeric release of a version string: ``"2.4.4"`` -> (2, 4, 4), ``"2.13.0+cu126"`` -> (2, 13, 0)."""
    return tuple(int(p) for p in re.match(r"\d+(\.\d+)*", version).group(0).split("."))


def split_requirement(requirement: str) -> Tuple[str, str]:
    """``"name>=floor"`` (a marker after ``;`` dropped) -> ``(name, floor)``; the form GeoPose's floors take."""
    name, floor = requirement.split(";")[0].split(">=")
    return name.strip(), floor.strip()


def _torch_requirement() -> Tuple[str, Tuple[int, int]]:
    """``(">=floor", (major, minor) of the oldest Python)`` of the torch line of ``requirements/torch.txt``."""
    line = next(r for r in read_requirements("torch") if normalized(split_requirement(r)[0]) == "torch")
    python = re.search(r"python_version\s*>=\s*['\"](\d+)\.(\d+)['\"]", line)
    return ">=" + split_requirement(line)[1], (int(python.group(1)), int(python.group(2))) if python else (3, 0)


#: pip requirements the Slicer module installs (``requirements/slicer.txt``); their floors are enforced, not only presence.
SLICER_REQUIREMENTS = read_requirements("slicer")
#: PyTorch's floor (``requirements/torch.txt``), as the PyTorch extension's ``torchVersionRequirement`` takes it,
#: and the oldest Python PyTorch is installed on (the line's marker: Slicer 5.10 and later).
TORCH_REQUIREMENT, TORCH_MINIMUM_PYTHON = _torch_requirement()
#: What the test-time optimisation adds, told to a user without PyTorch before it is offered. Numbers:
#: docs/benchmark/bench.md (42 held-out phantoms, 1 mm; the user's path: no segmentation given, rows "biplane:
#: greedy Refine + search" and "+ 25 TTO"; with the phantoms' labels given: the "upper bound (truth masks)" row);
#: the time: the 1 mm demo phantom on the 2-core VM, torch against the torch-free path (docs/pipeline_benchmark.md,
#: 2026-12-06, session 49: 12.3 against 6.1 s).
TTO_BENEFIT = (
    "Without PyTorch, GeoPose runs Init, Refine and the similarity search and skips the test-time "
    "optimisation (TTO), which refines both poses against the DSA runs. On 42 held-out phantom cases (1 mm CTAs) "
    "registered from the CTA and the two runs alone (vessels found in the CTA by GeoPose), the TTO took the mean "
    "carotid error at the detector from 3.2 mm to 1.1 mm; given each case's own vessel segmentation it reached "
    "0.7 mm (an upper bound). It adds about 6 s per registration on a 2-core CPU (less on a GPU)."
)


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
    found = []
    for requirement in requirements:
        name, floor = split_requirement(requirement)
        version = _installed_version(name, installed)
        if version is None or release(version) < release(floor):
            found.append(requirement)
    return found


def missing(requirements: Optional[Iterable[str]] = None) -> List[str]:
    """The ``requirements`` (default :data:`SLICER_REQUIREMENTS`) not installed at their floor version."""
    return unmet(SLICER_REQUIREMENTS if requirements is None else requirements)


def torch_supported() -> bool:
    """Whether this Python is one PyTorch is installed on (:data:`TORCH_MINIMUM_PYTHON`)."""
    return sys.version_info[:2] >= TORCH_MINIMUM_PYTHON


def torch_available() -> bool:
    """Whether PyTorch at :data:`TORCH_REQUIREMENT` or newer imports here (a broken install counts as missing): the
    one check of the Slicer module and of the registration engine."""
    if unmet(["torch" + TORCH_REQUIREMENT]):
        return False
    try:
        import torch  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


def shipped_too_old(requirements: Iterable[str], installed: Optional[Dict[str, str]] = None) -> List[Tuple[str, str]]:
    """``(requirement, installed version)`` for each requirement whose package is installed below its floor:
    meeting it would replace a package of Slicer's own Python, which GeoPose never does."""
    found = []
    for requirement in unmet(requirements, installed):
        version = _installed_version(split_requirement(requirement)[0], installed)
        if version is not None:
            found.append((requirement, version))
    return found


def check_installable(requirements: Iterable[str], installed: Optional[Dict[str, str]] = None) -> None:
    """Raise :class:`DependencyError` when a requirement is above an installed package (:func:`shipped_too_old`)."""
    too_old = shipped_too_old(requirements, installed)
    if too_old:
        raise DependencyError(
            "GeoPose needs " + ", ".join(f"{req} (this Slicer has {version})" for req, version in too_old)
            + ", and it never replaces a package of Slicer's own Python: use a newer Slicer release"
        )


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


@contextlib.contextmanager
def planned_install(python: str, requirements: Sequence[str]) -> Iterator[Tuple[Path, List[Tuple[str, str]]]]:
    """``(constraints file, [(name, version)] pip would install)`` for ``requirements`` with every installed
    distribution pinned (:func:`write_constraints`, :func:`plan_install`); the file lives until the block ends,
    so the install that follows uses the same constraints. Nothing is installed here."""
    with tempfile.TemporaryDirectory(prefix="geopose-install-") as folder:
        constraints = write_constraints(Path(folder))
        yield constraints, plan_install(python, requirements, constraints)


def install_missing(
    python: str,
    pip: Callable[[List[str], Path], None],
    ask: Optional[Callable[[List[Tuple[str, str]]], bool]] = None,
    testing: bool = False,
    requirements: Optional[Sequence[str]] = None,
) -> bool:
    """Install the unmet ``requirements`` (default :data:`SLICER_REQUIREMENTS`) into the Python ``python``
    with every installed distribution pinned (:func:`planned_install`): nothing installed is upgraded, and a
    requirement that would need that is refused before pip runs (:func:`check_installable`). ``ask(plan)``
    is shown the ``(name, version)`` pip resolved before anything is installed (False: nothing is, and this
    returns False); ``pip(requirements, constraints file)`` installs (the host's pip call, raising
    ``subprocess.CalledProcessError`` when pip fails). ``testing`` (an application in testing mode) installs
    nothing. Every refusal or failure is a one-line :class:`DependencyError`."""
    unmet_now = missing(requirements)
    if not unmet_now:
        return True
    check_installable(unmet_now)
    if testing:
        raise DependencyError(
            f"these Python packages are missing: {', '.join(unmet_now)}; Slicer runs in testing mode, in which "
            "GeoPose installs nothing: install them in a normal Slicer session first"
        )
    with planned_install(python, unmet_now) as (constraints, plan):
        if ask is not None and not ask(plan):
            return False
        try:
            pip(unmet_now, constraints)
        except subprocess.CalledProcessError as exc:
            raise DependencyError(
                f"pip could not install {', '.join(unmet_now)} (exit code {exc.returncode}; the Python console shows its "
                "output): nothing of Slicer's own packages was changed; check the internet connection and try again"
            ) from None
    importlib.invalidate_caches()
    still = missing(requirements)
    if still:
        raise DependencyError(
            f"these Python packages could not be installed: {', '.join(still)}; install them from Slicer's "
            "Python console with slicer.util.pip_install([...]) and restart Slicer"
        )
    return True
