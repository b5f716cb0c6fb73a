"""The default registration (``register_case`` with the CTA and the two runs, masks computed) with the opacified read
thinned by the two-view emission fit of ``selection_mlem.py`` wherever the TTO reads (at the networks' estimate; in
the mirror test at its start). One JSON line per validation seed (``turned_starts/default_path_rows.py``); compare
with ``experiments/tto_schedule/turned_starts/compare.py``.

    .venv/bin/python experiments/vessel_mask/selection_fit/selection_mlem_pipeline.py --blur 2 --share 0.05 --seeds 6030-6049 --out OUT.jsonl
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from selection_mlem import pipeline_parser, thinned  # noqa: E402  (geopose before torch)
from default_path_rows import run_seeds  # noqa: E402

from geopose.register import tto  # noqa: E402

ap = pipeline_parser(__doc__.splitlines()[0], 2.0)
args = ap.parse_args()
info: dict = {}


def fitted_read(volume, patient, rig, views, **kwargs):
    selection = thinned(volume, patient, rig, views, args.blur, args.share, **kwargs)
    if selection is not None and selection.applied:
        info.setdefault("reads", []).append(selection.kept_voxels)
    return selection


tto.read_opacified = fitted_read
run_seeds(list(args.seeds), args.out, f"mlem blur {args.blur} share {args.share}", info)
