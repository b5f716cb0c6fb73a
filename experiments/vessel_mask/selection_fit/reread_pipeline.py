"""The default registration (``register_case`` with the CTA and the two runs, masks computed) with the opacified vessels
read again during the TTO's full-size steps: at the given iterations, a run that holds a selection reads it anew at its
current pose, thinned by the two-view emission fit of ``selection_mlem.py`` (the first read, at the networks' estimate,
stays as it is). One JSON line per validation seed (``turned_starts/default_path_rows.py``); compare with
``experiments/tto_schedule/turned_starts/compare.py``.

    .venv/bin/python experiments/vessel_mask/selection_fit/reread_pipeline.py --at 15 18 21 --seeds 6030-6049 --out OUT.jsonl
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from selection_mlem import pipeline_parser, thinned  # noqa: E402  (geopose before torch)
from default_path_rows import run_seeds  # noqa: E402

from geopose.register import opacified, tto  # noqa: E402
from geopose.render.renderer import TorchRenderer  # noqa: E402

ap = pipeline_parser(__doc__.splitlines()[0], 0.7)
ap.add_argument("--at", type=int, nargs="+", default=[15, 18, 21])
args = ap.parse_args()
info: dict = {}


def fitted_read(run: tto.TTORun, patient: np.ndarray) -> opacified.VesselSelection | None:
    images = run.images
    views = [(v.name, v.vessels, v.detector) for v in images.views if images.vessel_term[v.name]]
    source = images.source_volume
    selection = thinned(source, patient, run.rig, views, args.blur, args.share, start="reread", iteration=run.it)
    if selection is None or not selection.applied:
        return None
    info.setdefault("rereads", []).append([run.it, selection.kept_voxels])
    return selection


original_advance = tto.TTORun.advance
original_rebound = tto.TTOImages.rebound


def rebound(self, renderer):
    out = original_rebound(self, renderer)
    out.source_volume = getattr(self, "source_volume", self.renderer.volume)
    return out


def advance(self, until, monitor):
    for at in sorted(args.at):
        if self.it < at < min(until, self.n + 1):
            original_advance(self, at, monitor)
        if self.it == at and self.vessel_selection is not None and self.joint:
            selection = fitted_read(self, self.patient_at(at - 1))
            if selection is not None:
                self.images = self.images.rebound(TorchRenderer(selection.volume, self.images.renderer.device))
                self.rescore_best()
                self.vessel_selection = selection
    original_advance(self, until, monitor)


tto.TTOImages.rebound = rebound
tto.TTORun.advance = advance
run_seeds(list(args.seeds), args.out, f"reread at {args.at} blur {args.blur} share {args.share}", info)
