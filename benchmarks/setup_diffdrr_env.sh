#!/usr/bin/env bash
# Build .venv-diffdrr/: a separate environment holding DiffDRR 0.6.1 next to our package,
# used only by the renderer validation and benchmark (benchmarks/*.py,
# Testing/Python/test_render_diffdrr.py). DiffDRR's full dependency list (pyvista[all],
# torchvision, timm, kornia, ...) clashes with the main stack, so DiffDRR is installed
# without dependencies plus only what diffdrr.{drr,data,pose,detector,renderers} import.
#
# Usage: benchmarks/setup_diffdrr_env.sh            (from the repository root)
#   PY=python3.11          interpreter for the venv
#   TORCH_SPEC=...         torch requirement (default torch==2.14.1, a second torch version
#                          besides the main venv's 2.13.0; use torch==2.13.0 for a CPU-only,
#                          smaller environment)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-python3.11}
VENV=${VENV:-.venv-diffdrr}
TORCH_SPEC=${TORCH_SPEC:-torch==2.14.1}
DIFFDRR_SPEC=${DIFFDRR_SPEC:-diffdrr==0.6.1}

"$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q "$TORCH_SPEC"
"$VENV/bin/python" -m pip install -q --no-deps "$DIFFDRR_SPEC"
# What DiffDRR's core modules import (drr: fastcore, torchio; pose: einops, scipy;
# data: pandas, nibabel, torchio), torchio's own dependencies, and ours (pydicom, onnx: geopose.dsa and geopose.bench import them).
"$VENV/bin/python" -m pip install -q fastcore einops scipy pandas nibabel torchio numpy SimpleITK pydicom onnx pytest matplotlib
"$VENV/bin/python" -m pip install -q --no-deps -e .
"$VENV/bin/python" - <<'PY'
import diffdrr, torch, geopose
from diffdrr.drr import DRR  # noqa: F401  (fails here if a dependency is missing)
print(f"diffdrr {diffdrr.__version__}, torch {torch.__version__}, geopose OK")
PY
