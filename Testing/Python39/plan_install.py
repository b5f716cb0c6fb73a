"""Run under Slicer 5.8's Python as GeoPose meets it (.venv-py39-slicer58: Python 3.9 with the packages
Slicer 5.8.1 ships at its versions, none of GeoPose's requirements): what ``pip install --dry-run``
would install for GeoPose's REQUIREMENTS with the module's constraints (GeoPoseLib.dependencies,
pinning every installed distribution) and without them. Prints one JSON object.

Usage: python plan_install.py REPOSITORY
"""

import ast
import json
import sys
from pathlib import Path

repo = Path(sys.argv[1])
sys.path.insert(0, str(repo / "GeoPoseModule"))
import tempfile  # noqa: E402

from GeoPoseLib import dependencies  # noqa: E402

tree = ast.parse((repo / "GeoPoseModule" / "GeoPose.py").read_text())
requirements = next(ast.literal_eval(n.value) for n in tree.body
                    if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "REQUIREMENTS")
installed = dependencies.installed_versions()
missing = dependencies.unmet(requirements)
with tempfile.TemporaryDirectory() as folder:
    constrained = dependencies.plan_install(sys.executable, missing, dependencies.write_constraints(Path(folder)))
unconstrained = dependencies.plan_install(sys.executable, missing, None)
print(json.dumps({
    "python": list(sys.version_info[:2]),
    "installed": installed,
    "missing": missing,
    "too_old": dependencies.shipped_too_old(requirements),
    "constrained": dict(constrained),
    "unconstrained": dict(unconstrained),
}))
