"""The default registration (``register_case`` with the CTA and the two runs, masks computed) with the opacified read
thinned by the two-view emission fit of ``selection_mlem.py`` wherever the TTO reads (at the networks' estimate; in
the mirror test at its start). One JSON line per validation seed (``turned_starts/default_path_rows.py``); compare
with ``experiments/tto_schedule/turned_starts/compare.py``.

    .venv/bin/python experiments/vessel_mask/selection_fit/selection_mlem_pipeline.py --blur 2 --share 0.05 --seeds 6030-6049 --out OUT.jsonl
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tto_schedule" / "turned_starts"))

import heldout  # noqa: E402,F401  (geopose before torch)
from default_path_rows import run_seeds  # noqa: E402
from selection_mlem import mlem_weights  # noqa: E402

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.register import opacified, tto  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--blur", type=float, default=2.0)
ap.add_argument("--share", type=float, default=0.05)
ap.add_argument("--seeds", type=seed_range, default=seed_range("6030-6049"))
ap.add_argument("--out", required=True)
args = ap.parse_args()
info: dict = {}


def fitted_read(volume, patient, rig, views, **kwargs):
    selection = opacified.read_opacified(volume, patient, rig, views, **kwargs)
    if selection is None or not selection.applied:
        return selection
    images = [(n, im, det) for n, im, det in views if np.max(im) > 0]
    w = mlem_weights(volume.centred_points(selection.kept_kji), patient, rig, images, args.blur)
    kept = selection.kept_kji[w >= args.share * np.percentile(w, 90)]
    info.setdefault("reads", []).append([len(selection.kept_kji), len(kept)])
    subset = volume.with_vessels(kept)
    return opacified.VesselSelection(subset.mask("vessels"), selection.vessel_voxels, len(kept), True,
                                     selection.start, selection.iteration, selection.patient_pose, kept, subset)


tto.read_opacified = fitted_read
run_seeds(list(args.seeds), args.out, f"mlem blur {args.blur} share {args.share}", info)
