"""Extension packaging: the module's imports exist, and the Extensions Index catalog entry
passes the checks the index runs (the real schema v1.0.2 from shared/slicer-api, category,
repository URL and name, CMake project name, contributors, icon and screenshot URLs, license).
What CMake builds and installs: test_extension_build.py."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from PIL import Image

REPO = Path(__file__).resolve().parents[2]
TOP_CMAKE = REPO / "CMakeLists.txt"
CATALOG = REPO / "GeoPose.json"

SCHEMA_URL = "https://raw.githubusercontent.com/Slicer/Slicer/main/Schemas/slicer-extension-catalog-entry-schema-v1.0.2.json"
#: Subset of the index's ACCEPTED_EXTENSION_CATEGORIES relevant here.
ACCEPTED_CATEGORIES = {"Registration", "Neuroimaging", "IGT", "Analysis"}
#: "First Last (Organisation)", as the Extensions Index writes contributors.
CONTRIBUTOR = re.compile(r"^[A-Z][\w'-]+( [A-Z][\w'-]+)+ \([^()]+\)$")


def test_module_imports_exist_in_the_library():
    """Every ``geopose`` module/name that GeoPose.py and its self-test GeoPoseTest.py import (most lazily) is there."""
    import importlib

    imports = [n for name in ("GeoPose.py", "GeoPoseTest.py")
               for n in ast.walk(ast.parse((REPO / "GeoPoseModule" / name).read_text()))
               if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("geopose")]
    assert imports
    for node in imports:
        if node.module == "geopose.mrml" or any(a.name == "mrml" for a in node.names):
            pytest.importorskip("slicer")
        mod = importlib.import_module(node.module)
        for alias in node.names:
            assert hasattr(mod, alias.name) or importlib.util.find_spec(f"{node.module}.{alias.name}"), (
                f"{node.module}.{alias.name} imported by the module does not exist"
            )


def test_library_never_imports_mrml_outside_its_package():
    offenders = []
    for path in (REPO / "Logic" / "geopose").rglob("*.py"):
        # mrml is the adapters; web (geopose view, the web extra) is a front end on MRML like the Slicer module
        if {"mrml", "web"} & set(path.relative_to(REPO / "Logic" / "geopose").parts):
            continue
        text = path.read_text()
        if re.search(r"^\s*(import slicer|from slicer|from \.+mrml|import geopose\.mrml|from geopose\.mrml)", text, re.M):
            offenders.append(str(path.relative_to(REPO)))
    assert not offenders


def _raw_url_to_path(url: str) -> Path:
    parts = urlsplit(url).path.strip("/").split("/")  # org / repo / branch / path...
    return REPO.joinpath(*parts[3:])


def test_catalog_entry_passes_index_checks():
    jsonschema = pytest.importorskip("jsonschema")
    from slicer_harness import slicer_api

    entry = json.loads(CATALOG.read_text())
    schema = json.loads((slicer_api() / "slicer-extension-catalog-entry-schema-v1.0.2.json").read_text())
    jsonschema.validate(entry, schema)
    assert entry["$schema"].split("#")[0] == SCHEMA_URL
    assert entry["build_dependencies"] == ["PyTorch"]  # PyTorchUtils comes with the PyTorch extension
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
    contributors = re.search(r'set\(EXTENSION_CONTRIBUTORS "([^"]+)"\)', cmake).group(1).split(", ")
    assert all(CONTRIBUTOR.match(c) for c in contributors), contributors
    assert re.search(r'set\(EXTENSION_DEPENDS "PyTorch"\)', cmake)
    # The URLs point at files committed in this repository.
    for u in [icon[0], *shots[0].split()]:
        assert _raw_url_to_path(u).is_file(), f"{u} names a file that is not in the repository"
    with Image.open(_raw_url_to_path(icon[0])) as im:
        assert im.format == "PNG" and im.size == (128, 128)
    assert (REPO / "LICENSE").is_file()
