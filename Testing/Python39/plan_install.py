"""Run under Slicer 5.8's Python as GeoPose meets it (.venv-py39-slicer58: Python 3.9 with the packages
Slicer 5.8.1 ships at its versions, none of GeoPose's requirements): what ``pip install --dry-run``
would install for the requirements the module installs (geopose.dependencies.SLICER_REQUIREMENTS)
with the module's constraints (pinning every installed distribution) and without them. Prints one JSON object.

Usage: python plan_install.py REPOSITORY
"""

import json
import sys
from pathlib import Path

repo = Path(sys.argv[1])
sys.path.insert(0, str(repo / "Logic"))
import tempfile  # noqa: E402

from geopose import dependencies  # noqa: E402  (standard library only, as the module imports it before installing)

requirements = dependencies.SLICER_REQUIREMENTS
installed = dependencies.installed_versions()
missing = dependencies.unmet(requirements)
with tempfile.TemporaryDirectory() as folder:
    constrained = dependencies.plan_install(sys.executable, missing, dependencies.write_constraints(Path(folder)))
unconstrained = dependencies.plan_install(sys.executable, missing, None)
print(json.dumps({
    "python": list(sys.version_info[:2]),
    "requirements": list(requirements),
    "heavy_modules": sorted(m for m in ("numpy", "SimpleITK", "pydicom", "vtk") if m in sys.modules),
    "installed": installed,
    "missing": missing,
    "too_old": dependencies.shipped_too_old(requirements),
    "constrained": dict(constrained),
    "unconstrained": dict(unconstrained),
}))
