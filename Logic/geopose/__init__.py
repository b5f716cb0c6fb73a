"""GeoPose: population-trained C-arm pose estimation for CTA-to-DSA registration.

The library behind the 3D Slicer extension; it imports without Slicer.
"""

import os

__version__ = "0.1.0"

# Idle OpenMP threads sleep instead of spinning: on a laptop that runs other work, spinning
# threads made 2-thread torch 4x slower (docs/pipeline_benchmark.md). Takes effect when
# geopose is imported before torch (the CLI does); an explicit setting is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
