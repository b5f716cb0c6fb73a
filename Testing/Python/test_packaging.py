"""Extension packaging: CMake covers every file the module needs, and the Extensions
Index catalog entry passes the checks the index runs (schema v1.0.2 fields, category,
repository URL and name, CMake project name, icon and screenshot URLs, license)."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from PIL import Image

REPO = Path(__file__).resolve().parents[2]
MODULE_CMAKE = REPO / "GeoPoseModule" / "CMakeLists.txt"
TOP_CMAKE = REPO / "CMakeLists.txt"
CATALOG = REPO / "GeoPose.json"

#: Fields of slicer-extension-catalog-entry-schema-v1.0.2 (additionalProperties: false) and their types.
SCHEMA_FIELDS = {
    "$schema": str, "category": str, "scm_url": str, "scm_revision": str, "scm_type": str,
    "build_dependencies": list, "dicom_support_rule": str, "build_subdirectory": str, "enabled": bool, "tier": int,
}
SCHEMA_REQUIRED = ("$schema", "category", "scm_url")
SCHEMA_URL = "https://raw.githubusercontent.com/Slicer/Slicer/main/Schemas/slicer-extension-catalog-entry-schema-v1.0.2.json"
#: Subset of the index's ACCEPTED_EXTENSION_CATEGORIES relevant here.
ACCEPTED_CATEGORIES = {"Registration", "Neuroimaging", "IGT", "Analysis"}


def _cmake_globs(text: str, variables: dict[str, Path]) -> list[str]:
    """Expand every ``file(GLOB_RECURSE VAR RELATIVE base patterns...)`` of a CMake file; returns repo-relative paths."""
    found = []
    for m in re.finditer(r"file\(\s*GLOB_RECURSE\s+(\w+)\s+RELATIVE\s+(\S+)\s+(.*?)\)", text, re.S):
        for pattern in m.group(3).split():
            for name, value in variables.items():
                pattern = pattern.replace("${%s}" % name, str(value))
            root, _, glob = pattern.partition("*")
            base = Path(root).resolve()
            # CMake's GLOB_RECURSE matches the file-name pattern in every subfolder.
            for path in base.parent.rglob(Path(pattern).name) if "/" not in glob else base.rglob(glob):
                if path.is_file() and str(path.resolve()).startswith(str(base)):
                    found.append(str(path.resolve().relative_to(REPO)))
    return found


def _cmake_variables() -> dict[str, Path]:
    here = MODULE_CMAKE.parent
    return {
        "CMAKE_CURRENT_SOURCE_DIR": here,
        "GEOPOSE_LIBRARY_DIR": (here / ".." / "Logic").resolve(),
        "GEOPOSE_RESOURCES_ROOT": (here / "..").resolve(),
    }


def _needed_files() -> set[str]:
    lib = {str(p.relative_to(REPO)) for p in (REPO / "Logic" / "geopose").rglob("*.py")}
    res = {str(p.relative_to(REPO)) for p in (REPO / "Resources" / "Models").iterdir() if p.is_file()}
    return lib | res | {"Resources/UI/GeoPose.ui", "Resources/Icons/GeoPose.png"}


def test_cmake_packages_every_library_file_and_resource():
    text = MODULE_CMAKE.read_text()
    covered = set(_cmake_globs(text, _cmake_variables()))
    missing = sorted(_needed_files() - covered)
    assert not missing, f"not packaged by GeoPoseModule/CMakeLists.txt: {missing}"
    assert re.search(r"slicerMacroBuildScriptedModule\(.*?SCRIPTS \$\{MODULE_PYTHON_SCRIPTS\}", text, re.S)
    scripts = re.search(r"set\(MODULE_PYTHON_SCRIPTS(.*?)\)", text, re.S).group(1).split()
    module_py = {p.name for p in MODULE_CMAKE.parent.glob("*.py")}
    assert module_py == {s.replace("${MODULE_NAME}", "GeoPose") for s in scripts}


def test_glob_evaluator_catches_an_omission(tmp_path):
    """The coverage check above would fail if a needed file fell outside the globs."""
    text = MODULE_CMAKE.read_text().replace("${GEOPOSE_RESOURCES_ROOT}/Resources/Models/*", "")
    assert any(p.startswith("Resources/Models/") for p in _needed_files() - set(_cmake_globs(text, _cmake_variables())))


def test_module_imports_exist_in_the_library():
    """Every ``geopose`` module/name that GeoPose.py imports lazily is there."""
    import importlib

    tree = ast.parse((REPO / "GeoPoseModule" / "GeoPose.py").read_text())
    imports = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("geopose")]
    assert imports
    for node in imports:
        if node.module == "geopose.mrml" or any(a.name == "mrml" for a in node.names):
            pytest.importorskip("slicer")
        mod = importlib.import_module(node.module)
        for alias in node.names:
            assert hasattr(mod, alias.name) or importlib.util.find_spec(f"{node.module}.{alias.name}"), (
                f"{node.module}.{alias.name} imported by GeoPose.py does not exist"
            )


def test_library_never_imports_mrml_outside_its_package():
    offenders = []
    for path in (REPO / "Logic" / "geopose").rglob("*.py"):
        if "mrml" in path.relative_to(REPO / "Logic" / "geopose").parts:
            continue
        text = path.read_text()
        if re.search(r"^\s*(import slicer|from slicer|from \.+mrml|import geopose\.mrml|from geopose\.mrml)", text, re.M):
            offenders.append(str(path.relative_to(REPO)))
    assert not offenders


def _raw_url_to_path(url: str) -> Path:
    parts = urlsplit(url).path.strip("/").split("/")  # org / repo / branch / path...
    return REPO.joinpath(*parts[3:])


def test_catalog_entry_passes_index_checks():
    entry = json.loads(CATALOG.read_text())
    for key in SCHEMA_REQUIRED:
        assert entry.get(key), f"{key} is required by the catalog schema"
    for key, value in entry.items():
        assert key in SCHEMA_FIELDS, f"{key} is not allowed by the catalog schema (additionalProperties false)"
        assert isinstance(value, SCHEMA_FIELDS[key]), f"{key} must be {SCHEMA_FIELDS[key].__name__}"
    assert entry["$schema"].split("#")[0] == SCHEMA_URL
    assert all(isinstance(d, str) for d in entry.get("build_dependencies", []))
    assert 1 <= entry.get("tier", 1) <= 5
    assert entry.get("scm_type", "git") in ("git", "local")
    assert entry["category"] in ACCEPTED_CATEGORIES and entry["category"] == "Registration"
    url = urlsplit(entry["scm_url"])
    assert url.scheme in ("git", "https") and "://" in entry["scm_url"]
    assert "slicer" in Path(url.path).stem.lower(), "the index wants the repository name to contain 'Slicer'"
    # The CMake project name equals the catalog file name, and the metadata the index reads is there.
    cmake = TOP_CMAKE.read_text()
    assert re.findall(r"project\s*\(\s*([^\s\)]+)", cmake, re.I)[0] == CATALOG.stem
    icon = re.findall(r'set\s*\(EXTENSION_ICONURL\s*"([^"]+)"[ ]*\)', cmake, re.I)
    shots = re.findall(r'set\s*\(EXTENSION_SCREENSHOTURLS\s*"([^"]+)"\)', cmake, re.I)
    assert icon and icon[0].startswith("http") and shots and all(u.startswith("http") for u in shots[0].split())
    assert re.search(r'set\(EXTENSION_CATEGORY "Registration"\)', cmake)
    assert re.search(r'set\(EXTENSION_HOMEPAGE "([^"]+)"\)', cmake).group(1) == entry["scm_url"]
    for key in ("EXTENSION_CONTRIBUTORS", "EXTENSION_DESCRIPTION", "EXTENSION_DEPENDS"):
        assert re.search(rf'set\({key} "[^"]+"\)', cmake), f"{key} missing from CMakeLists.txt"
    # The URLs point at files committed in this repository.
    for u in [icon[0], *shots[0].split()]:
        assert _raw_url_to_path(u).is_file(), f"{u} names a file that is not in the repository"
    with Image.open(_raw_url_to_path(icon[0])) as im:
        assert im.format == "PNG" and im.size == (128, 128)
    assert (REPO / "LICENSE").is_file()
