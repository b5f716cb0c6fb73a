"""Slicer 5.8 runs Python 3.9 with numpy 1.26.4 and pydicom 2.4.4: the torch-free registration and
the DICOM writer run there (``.venv-py39``, built by ``make test`` from Testing/Python39/requirements.txt)
and give the poses this environment's onnxruntime engine gives; and the module's first install,
planned by pip in an environment holding only what Slicer 5.8.1 ships (``.venv-py39-slicer58``,
from Testing/Python39/slicer58.txt), changes none of Slicer's packages."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from geopose import dependencies
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.geometry import poses as N
from geopose.options import RegistrationOptions, TTOSchedule
from geopose.phantom.cli import write_phantom
from geopose.register import register_case
from geopose.register.record import build_record

REPO = Path(__file__).resolve().parents[2]
PY39 = REPO / ".venv-py39" / "bin" / "python"
PY39_SLICER = REPO / ".venv-py39-slicer58" / "bin" / "python"
CHECK = REPO / "Testing" / "Python39" / "check_library.py"
PLAN = REPO / "Testing" / "Python39" / "plan_install.py"
REQUIREMENTS_39 = REPO / "Testing" / "Python39" / "requirements.txt"
SLICER_58 = REPO / "Testing" / "Python39" / "slicer58.txt"


def _module_requirements() -> tuple[str, ...]:
    """What the module installs into Slicer (geopose.dependencies, read from Logic/geopose/requirements/slicer.txt)."""
    return dependencies.SLICER_REQUIREMENTS


def _lines(path: Path) -> list[str]:
    """The requirement lines of a pip requirements file, ``-r`` includes followed (relative to the file, as pip reads them)."""
    lines = []
    for line in (raw.split("#")[0].strip() for raw in path.read_text().splitlines()):
        if line.startswith("-r "):
            lines += _lines(path.parent / line[3:].strip())
        elif line:
            lines.append(line)
    return lines


def test_the_python39_environment_holds_the_module_requirements_at_slicer_58s_versions():
    shipped = _lines(SLICER_58)
    assert {"numpy==1.26.4", "pydicom==2.4.4", "Pillow==10.1.0"} <= set(shipped)  # what Slicer 5.8.1 ships
    lines = _lines(REQUIREMENTS_39)
    assert lines == shipped + list(_module_requirements())  # Slicer 5.8's packages, then the module's requirements
    assert "-r ../../Logic/geopose/requirements/slicer.txt" in REQUIREMENTS_39.read_text()  # the one list, included
    # What Slicer 5.8 ships meets the module's floors (pydicom 2.4.4, Pillow 10.1.0): the rest is what it lacks.
    pins = {dependencies.normalized(name): version for name, version in (line.split("==") for line in shipped)}
    assert dependencies.unmet(_module_requirements(), pins) == [r for r in _module_requirements() if r not in ("pydicom>=2.4", "Pillow>=10")]


def test_a_first_install_on_slicer_58_changes_none_of_its_packages():
    """pip's own resolution (``pip install --dry-run``, nothing installed) of the module's missing
    requirements in Slicer 5.8's environment, with the constraints the module writes: every package
    Slicer ships keeps its version (numpy 1.26.4: pylibjpeg-libjpeg 2.3 and pylibjpeg-openjpeg 2.5 need
    numpy 2, so older releases are picked); without constraints pip would install numpy 2."""
    if not PY39_SLICER.is_file():
        pytest.skip("no .venv-py39-slicer58: `make test` builds it (python3.9 -m venv + Testing/Python39/slicer58.txt)")
    run = subprocess.run([str(PY39_SLICER), str(PLAN), str(REPO)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-4000:]
    out = json.loads(run.stdout.splitlines()[-1])
    assert out["python"] == [3, 9] and out["installed"]["numpy"] == "1.26.4" and out["too_old"] == []
    # geopose.dependencies runs there on the standard library alone (numpy is Slicer's; it is not imported)
    assert out["requirements"] == list(_module_requirements()) and out["heavy_modules"] == []
    assert set(out["missing"]) == set(_module_requirements()) - {"pydicom>=2.4", "Pillow>=10"}
    constrained, unconstrained = out["constrained"], out["unconstrained"]
    assert not set(constrained) & set(out["installed"]), "a package Slicer ships would be replaced"
    assert {re.split(">=", r)[0].lower() for r in out["missing"]} <= set(constrained)
    assert unconstrained["numpy"].startswith("2."), "pip no longer needs numpy 2 here: the check lost its point"


def test_torch_free_registration_and_dicom_writer_on_python39_with_pydicom_2_4(tmp_path):
    if not PY39.is_file():
        pytest.skip("no .venv-py39: `make test` builds it (python3.9 -m venv + Testing/Python39/requirements.txt)")
    write_phantom(5003, tmp_path, spacing_mm=4.0, max_matrix_px=128)
    run = subprocess.run([str(PY39), str(CHECK), str(tmp_path), str(REPO)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-4000:]
    out = json.loads(run.stdout.splitlines()[-1])
    assert out["python"] == [3, 9] and out["pydicom"] == "2.4.4" and not out["torch_loaded"] and out["engine"] == "onnxruntime"
    assert out["written_frames_equal"] and out["written_geometry_equal"]
    runs = {key: read_dsa(tmp_path / f"dsa_{key}.dcm") for key in ("pa", "lat")}
    options = RegistrationOptions(backend="onnxruntime", tto=TTOSchedule(iterations=0))
    want = build_record(register_case(load_cta(tmp_path / "cta.nii.gz"), runs, options=options), runs)
    for key in runs:
        got, ref = np.asarray(out["pose_centred"][key]), np.asarray(want["views"][key]["pose_centred"])
        np.testing.assert_allclose(got[:3, 3], ref[:3, 3], atol=0.5)  # mm
        assert np.degrees(N.rotation_angle_rad(got[:3, :3].T @ ref[:3, :3])) < 0.1
