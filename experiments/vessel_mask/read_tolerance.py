"""Drift of the default TTO started at the truth (masks computed, as ``selection_oracle.py``) with the opacified read's
tolerance varied: its blur (px at the TTO size) and threshold (share of the vessel image's maximum), nothing dropped.
One JSON line per seed; a variant's "selection" counts are the last read that was applied (a read under
``OPACIFIED_MIN_FRACTION`` leaves the previous one's). Ran at 60a693c (session 43; rows ``read_tolerance.jsonl``).

    .venv/bin/python experiments/vessel_mask/read_tolerance.py --seeds 6020-6028 --doc OUT.jsonl
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from selection_oracle import DROPPED, OracleRead, drift_rows  # noqa: E402

from geopose.register import opacified  # noqa: E402

#: Variant -> (blur px, threshold); the first is the default read.
READS = {"2px 0.02": (2.0, 0.02), "1px 0.02": (1.0, 0.02), "1px 0.1": (1.0, 0.1), "1px 0.3": (1.0, 0.3),
         "2px 0.3": (2.0, 0.3), "0.7px 0.3": (0.7, 0.3)}


def reading(blur_px: float, threshold: float):
    def setup(read: OracleRead) -> None:
        read.drop = DROPPED["computed"]
        opacified.OPACIFIED_BLUR_PX, opacified.OPACIFIED_THRESHOLD = blur_px, threshold
    return setup


if __name__ == "__main__":
    drift_rows({name: reading(*r) for name, r in READS.items()}, __doc__.splitlines()[0], "6020-6028")
