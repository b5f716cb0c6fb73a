"""A real CMake configure, build and install of the extension with Slicer's and CTK's own macros.

``shared/slicer-api`` holds ``SlicerMacroBuildScriptedModule.cmake`` (per Slicer release) and CTK's
``ctkMacroCompilePythonScript.cmake``. The only stand-in is a ``SlicerConfig.cmake`` that sets
what a Slicer build tree gives an extension of scripted modules (``Slicer_USE_PYTHONQT=ON``, the
qt-scripted-modules folders, ``CTK_CMAKE_DIR``) and includes those real macro files; the
extension-config and packaging steps of a Slicer build are empty and print the extension's
metadata instead. ``cmake`` comes from PyPI (pyproject's test dependencies).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

import slicer_harness as H

REPO = H.REPO
CMAKE = shutil.which("cmake", path=str(Path(sys.executable).parent)) or shutil.which("cmake")
METADATA = ("EXTENSION_HOMEPAGE", "EXTENSION_CATEGORY", "EXTENSION_CONTRIBUTORS", "EXTENSION_DEPENDS", "EXTENSION_ICONURL")

if CMAKE is None:
    pytest.skip("cmake not found: pip install cmake (a test dependency)", allow_module_level=True)
if not H.slicer_api().is_dir():
    pytest.skip(f"Slicer's CMake macros not found at {H.slicer_api()}", allow_module_level=True)


def _slicer_config(folder: Path, tag: str) -> Path:
    major, minor = tag.lstrip("v").split(".")[:2]
    folder.mkdir(parents=True)
    (folder / "SlicerConfig.cmake").write_text(f"""
set(Slicer_USE_PYTHONQT ON)
set(Slicer_QTSCRIPTEDMODULES_LIB_DIR "lib/Slicer-{major}.{minor}/qt-scripted-modules")
set(Slicer_INSTALL_QTSCRIPTEDMODULES_LIB_DIR "./${{Slicer_QTSCRIPTEDMODULES_LIB_DIR}}")
set(CTK_CMAKE_DIR "{H.slicer_api() / 'ctk-cmake'}")
set(Slicer_USE_FILE "${{CMAKE_CURRENT_LIST_DIR}}/UseSlicer.cmake")
set(Slicer_EXTENSION_GENERATE_CONFIG "${{CMAKE_CURRENT_LIST_DIR}}/ExtensionMetadata.cmake")
set(Slicer_EXTENSION_CPACK "${{CMAKE_CURRENT_LIST_DIR}}/ExtensionMetadata.cmake")
""")
    (folder / "UseSlicer.cmake").write_text(f"""
include(${{CTK_CMAKE_DIR}}/ctkFunctionExtractOptimizedLibrary.cmake)
include(${{CTK_CMAKE_DIR}}/ctkMacroCompilePythonScript.cmake)
include("{H.slicer_api() / tag / 'cmake' / 'SlicerMacroBuildScriptedModule.cmake'}")
""")
    (folder / "ExtensionMetadata.cmake").write_text(
        "".join(f'message(STATUS "{k}=${{{k}}}")\n' for k in METADATA)
    )
    return folder


def _python_hints() -> list[str]:
    """Where CTK's byte-compile step finds Python (Slicer passes its own)."""
    lib = Path(sysconfig.get_config_var("LIBDIR") or "") / (sysconfig.get_config_var("LDLIBRARY") or "")
    return [f"-DPYTHON_EXECUTABLE={sys.executable}", f"-DPYTHON_INCLUDE_DIR={sysconfig.get_paths()['include']}",
            f"-DPYTHON_LIBRARY={lib}"]


def configure_build_install(source: Path, tag: str, work: Path) -> tuple[subprocess.CompletedProcess, Path]:
    """Configure ``source`` (the extension's top folder), build and install it; returns the configure run and the prefix."""
    config = _slicer_config(work / "slicer", tag)
    build, prefix = work / "build", work / "install"
    configure = subprocess.run(
        [CMAKE, "-S", str(source), "-B", str(build), f"-DSlicer_DIR={config}", "-DBUILD_TESTING=OFF", "-Wno-dev",
         f"-DCMAKE_INSTALL_PREFIX={prefix}", *_python_hints()],
        capture_output=True, text=True, timeout=300,
    )
    if configure.returncode == 0:
        for step in ([CMAKE, "--build", str(build)], [CMAKE, "--install", str(build)]):
            done = subprocess.run(step, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return configure, prefix


@pytest.fixture(scope="module", params=H.SLICER_TAGS)
def installed(request, tmp_path_factory):
    configure, prefix = configure_build_install(REPO, request.param, tmp_path_factory.mktemp(f"cmake-{request.param}"))
    assert configure.returncode == 0, configure.stdout[-3000:] + configure.stderr[-3000:]
    major, minor = request.param.lstrip("v").split(".")[:2]
    return configure, prefix / "lib" / f"Slicer-{major}.{minor}" / "qt-scripted-modules"


def test_the_installed_tree_holds_the_module_library_and_resources_only(installed):
    configure, modules = installed
    files = {str(p.relative_to(modules)) for p in modules.rglob("*") if p.is_file()}
    assert "GeoPose.py" in files
    library = {str(p.relative_to(REPO / "Logic")) for p in (REPO / "Logic" / "geopose").rglob("*")
               if p.is_file() and "__pycache__" not in p.parts}
    assert library <= files, sorted(library - files)[:5]
    assert {"geopose/dependencies.py", "geopose/requirements/slicer.txt", "geopose/requirements/torch.txt"} <= library
    resources = {str(p.relative_to(REPO)) for p in (REPO / "Resources").rglob("*") if p.is_file()}
    assert resources <= files, sorted(resources - files)
    assert {"Resources/UI/GeoPose.ui", "Resources/Icons/GeoPose.png", "Resources/Models/manifest.json"} <= files
    manifest = json.loads((modules / "Resources" / "Models" / "manifest.json").read_text())
    assert manifest and all((modules / "Resources" / "Models" / Path(f).name).is_file()
                            for f in {e["file"] for e in manifest.get("models", {}).values()} if manifest.get("models"))
    # Nothing of Testing/, benchmarks/ or experiments/: no file of theirs by name (unless the library has
    # one of the same name, e.g. run.py) nor under their folder names.
    outside = {p.name for top in ("Testing", "benchmarks", "experiments") for p in (REPO / top).rglob("*") if p.is_file()}
    outside -= {Path(f).name for f in library | resources}
    leaked = sorted(f for f in files if Path(f).name in outside or f.split("/")[0] in ("Testing", "benchmarks", "experiments"))
    assert not leaked, leaked
    module = {str(p.relative_to(REPO / "GeoPoseModule")) for p in (REPO / "GeoPoseModule").rglob("*.py")}
    assert {"GeoPose.py", "GeoPoseTest.py"} <= module <= files, sorted(module - files)
    extra = sorted(f for f in files if not f.endswith(".pyc") and f not in library | resources | module)
    assert not extra, extra


def test_the_extension_metadata_cmake_reads(installed):
    configure, _ = installed
    meta = dict(line.split("-- ", 1)[1].split("=", 1) for line in configure.stdout.splitlines() if line.startswith("-- EXTENSION_"))
    assert meta["EXTENSION_DEPENDS"] == "PyTorch" and meta["EXTENSION_CATEGORY"] == "Registration"
    tree = __import__("ast").parse(H.MODULE_FILE.read_text())
    contributors = next(__import__("ast").literal_eval(n.value) for n in tree.body
                        if isinstance(n, __import__("ast").Assign) and getattr(n.targets[0], "id", "") == "CONTRIBUTORS")
    assert meta["EXTENSION_CONTRIBUTORS"] == ", ".join(contributors)


def test_the_installed_module_runs_from_the_installed_tree(installed, tmp_path):
    """The installed GeoPose.py finds the installed library, panel and icon (a process without ../Logic)."""
    _, modules = installed
    probe = tmp_path / "probe.py"
    probe.write_text(f"""
import sys, types
from pathlib import Path
import slicer
import slicer_harness as H
module = H.load_module({H.SLICER_TAGS[-1]!r}, slicer.vtkMRMLScene(), path=Path({str(modules / 'GeoPose.py')!r}))
import geopose
parent = types.SimpleNamespace(path=module.__file__)
module.GeoPose(parent)
p = module.GeoPoseLogic().getParameterNode()
print(geopose.__file__)
print(module.resourceFile("UI/GeoPose.ui"))
print(parent.icon.path)
print(module.GeoPoseLogic.defaultModelsFolder())
print(sys.modules["GeoPoseTest"].__file__)
print(module.dependencies.REQUIREMENTS_FOLDER / "slicer.txt")
assert module.dependencies.SLICER_REQUIREMENTS and module.dependencies.TORCH_REQUIREMENT.startswith(">=")
""")
    env = {"PYTHONPATH": str(REPO / "Testing" / "Python"), "PATH": "/usr/bin:/bin"}
    run = subprocess.run([sys.executable, str(probe)], capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.split()
    assert all(line.startswith(str(modules)) for line in lines), lines
