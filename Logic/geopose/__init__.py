"""GeoPose: population-trained C-arm pose estimation for CTA-to-DSA registration.

The library behind the 3D Slicer extension; it imports without Slicer.
"""

import os
import sys

__version__ = "0.1.0"

# Idle OpenMP threads sleep instead of spinning: on a laptop that runs other work, spinning
# threads made 2-thread torch 4x slower, and two registrations at once 11x (docs/pipeline_benchmark.md).
# Takes effect when geopose is imported before torch (the CLI does); an explicit setting is kept.
_POLICY_GIVEN = "OMP_WAIT_POLICY" in os.environ
_TORCH_FIRST = "torch" in sys.modules
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
#: Whether PyTorch's idle OpenMP threads sleep: not when torch was imported before geopose without
#: OMP_WAIT_POLICY (its OpenMP runtime had read the default, spinning), nor when the environment asks otherwise.
OPENMP_THREADS_SLEEP = os.environ["OMP_WAIT_POLICY"].upper() == "PASSIVE" and (_POLICY_GIVEN or not _TORCH_FIRST)
