"""One place for GeoPose's Python requirements: ``Logic/geopose/requirements/*.txt``. setuptools reads
them for the package's metadata (pyproject.toml's dynamic dependencies and extras), the library for the
Slicer module (``geopose.dependencies``), Testing/Python39/requirements.txt includes the module's list;
the Makefile's exact torch pin is the release of the torch floor."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from email.parser import Parser
from pathlib import Path

import pytest

from geopose import dependencies as D

REPO = Path(__file__).resolve().parents[2]
FOLDER = REPO / "Logic" / "geopose" / "requirements"


def test_the_library_reads_the_requirement_files():
    assert D.REQUIREMENTS_FOLDER == FOLDER
    assert D.SLICER_REQUIREMENTS == (
        "SimpleITK>=2.3", "pydicom>=2.4", "pylibjpeg>=2.0", "pylibjpeg-libjpeg>=2.1", "pylibjpeg-openjpeg>=2.3",
        "pylibjpeg-rle>=2.0", "onnxruntime>=1.18", "Pillow>=10")
    assert (D.TORCH_REQUIREMENT, D.TORCH_MINIMUM_PYTHON) == (">=2.13", (3, 10))
    assert D.read_requirements("torch") == ("torch>=2.13; python_version >= '3.10'", "onnx>=1.16")


def test_requirement_files_hold_what_setuptools_and_the_module_read():
    """Comments only on whole lines (setuptools drops no inline comment); the module's list is plain
    ``name>=floor`` lines, the only form it checks."""
    for path in FOLDER.glob("*.txt"):
        for line in path.read_text().splitlines():
            assert line.startswith("#") or "#" not in line, f"{path.name}: inline comment in {line!r}"
    assert all(re.fullmatch(r"[A-Za-z0-9_.-]+>=\d+(\.\d+)*", r) for r in D.SLICER_REQUIREMENTS)


def test_pyproject_takes_its_requirements_from_the_files():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert set(project["project"]["dynamic"]) == {"dependencies", "optional-dependencies"}
    assert "dependencies" not in project["project"] and "optional-dependencies" not in project["project"]
    dynamic = project["tool"]["setuptools"]["dynamic"]
    rel = "Logic/geopose/requirements/"
    assert dynamic["dependencies"] == {"file": [rel + "slicer.txt", rel + "standalone.txt"]}
    assert dynamic["optional-dependencies"] == {x: {"file": [f"{rel}{x}.txt"]} for x in ("torch", "test", "web")}
    assert {p.stem for p in FOLDER.glob("*.txt")} == {"slicer", "standalone", "torch", "test", "web"}
    assert project["tool"]["setuptools"]["package-data"]["geopose"] == ["requirements/*.txt"]


def test_the_built_wheel_states_the_files_requirements_and_ships_them(tmp_path):
    """setuptools (this environment's, no download) builds the wheel of a copy of the project: its
    Requires-Dist are the files' lines and the files are in it, where geopose.dependencies reads them."""
    pytest.importorskip("setuptools")
    src = tmp_path / "src"
    shutil.copytree(REPO / "Logic", src / "Logic", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, src / name)
    run = subprocess.run([sys.executable, "-c", "import sys; from setuptools import build_meta as b; "
                          "print(b.build_wheel(sys.argv[1]))", str(tmp_path / "dist")],
                         cwd=src, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    with zipfile.ZipFile(tmp_path / "dist" / run.stdout.split()[-1]) as wheel:
        names = wheel.namelist()
        meta = Parser().parsestr(wheel.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode())
    assert {f"geopose/requirements/{p.name}" for p in FOLDER.glob("*.txt")} <= set(names)
    assert "geopose/dependencies.py" in names

    def spec(line: str, extra: str | None = None) -> str:
        req, _, marker = (part.strip() for part in line.partition(";"))
        marker = marker.replace("'", '"')
        marker = " and ".join(m for m in (marker, f'extra == "{extra}"' if extra else "") if m)
        return f"{req}; {marker}" if marker else req

    want = [spec(r) for r in D.read_requirements("slicer") + D.read_requirements("standalone")]
    want += [spec(r, x) for x in ("torch", "test", "web") for r in D.read_requirements(x)]
    assert meta.get_all("Requires-Dist") == want
    assert meta.get_all("Provides-Extra") == ["torch", "test", "web"]


def test_the_torch_floor_is_the_makefiles_pinned_release():
    """``>=2.13`` is said once (torch.txt); the Makefile installs exactly that release (its CPU build)."""
    (pin,) = re.findall(r"pip install -q torch==([\d.]+)", (REPO / "Makefile").read_text())
    floor = D.TORCH_REQUIREMENT.removeprefix(">=")
    assert D.release(pin)[:len(D.release(floor))] == D.release(floor) and D.unmet(["torch" + D.TORCH_REQUIREMENT], {"torch": pin}) == []
    assert D.split_requirement(next(r for r in D.read_requirements("torch") if r.startswith("torch")))[1] == floor


def test_the_module_and_the_python39_environment_state_no_requirement_of_their_own():
    """GeoPose.py names no version floor (it uses geopose.dependencies); Python 3.9's environment includes slicer.txt."""
    module = (REPO / "GeoPoseModule" / "GeoPose.py").read_text()
    assert not re.search(r"""["'][A-Za-z-]+\s*>=\s*\d""", module) and "2.13" not in module
    assert "-r ../../Logic/geopose/requirements/slicer.txt" in (REPO / "Testing" / "Python39" / "requirements.txt").read_text()


def test_unmet_and_too_old_compare_releases():
    installed = {"pydicom": "2.4.4", "pillow": "10.1.0", "torch": "2.13.0+cu126"}
    assert D.unmet(["pydicom>=2.4", "Pillow>=10", "SimpleITK>=2.3"], installed) == ["SimpleITK>=2.3"]
    assert D.unmet(["pydicom>=3.0"], installed) == ["pydicom>=3.0"] and D.unmet(["torch>=2.13"], installed) == []
    assert D.shipped_too_old(["pydicom>=3.0", "SimpleITK>=2.3"], installed) == [("pydicom>=3.0", "2.4.4")]
    with pytest.raises(D.DependencyError, match=r"GeoPose needs pydicom>=3.0 \(this Slicer has 2.4.4\)"):
        D.check_installable(["pydicom>=3.0"], installed)
    assert D.pip_constraints({"b": "1", "a": "2"}) == "a==2\nb==1\n"


def test_install_missing_plans_asks_installs_and_checks(monkeypatch, tmp_path):
    """The install flow the Slicer module hands its dialog and pip call to (recorded here; the module's own
    tests drive it through GeoPoseLogic.ensureDependencies on Slicer's Python layer)."""
    probe = "geopose-absent-probe>=1.0"
    plans, installed = [], []
    monkeypatch.setattr(D, "plan_install", lambda python, reqs, constraints: plans.append((python, list(reqs), constraints.read_text()))
                        or [("geopose-absent-probe", "1.2")])
    assert D.install_missing("py", installed.append, requirements=["pytest>=1"]) is True and plans == []  # nothing missing
    assert D.install_missing("py", lambda reqs, constraints: installed.append(reqs), ask=lambda plan: False,
                             requirements=[probe]) is False
    assert installed == [] and plans[0][:2] == ("py", [probe]) and "pytest==" in plans[0][2]
    with pytest.raises(D.DependencyError, match="could not be installed: geopose-absent-probe>=1.0"):
        D.install_missing("py", lambda reqs, constraints: installed.append((reqs, constraints.is_file())),
                          ask=lambda plan: plan == [("geopose-absent-probe", "1.2")], requirements=[probe])
    assert installed == [([probe], True)]  # pip ran with the constraints file still there

    def failing(reqs, constraints):
        raise subprocess.CalledProcessError(1, ["pip"])

    with pytest.raises(D.DependencyError, match=r"pip could not install geopose-absent-probe>=1.0 \(exit code 1"):
        D.install_missing("py", failing, requirements=[probe])
    with pytest.raises(D.DependencyError, match="testing mode"):
        D.install_missing("py", failing, testing=True, requirements=[probe])
