"""What the opacified read keeps, by phantom label, read at the truth, at the networks' estimate and at the
registration's result (``register_case``, masks computed), as read (2 px, 0.02) and thinned by the two-view emission fit
(``selection_mlem.py``) at several blurs, with and without each view's best shift (within 3 px) before the fit.
Prints "arteries/veins" kept per variant.

    .venv/bin/python experiments/vessel_mask/selection_fit/composition.py 6034 6031 6035 6032
"""
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from selection_mlem import ARTERIES, VEINS, mlem_weights  # noqa: E402  (geopose before torch, via heldout)

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.cta.io import load_cta  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import Objective  # noqa: E402
from geopose.register import opacified, register_case  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.engine import torch_renderer_for  # noqa: E402
from geopose.register.tto import TTOImages, tto_views  # noqa: E402

models = load_models(runtime="torch")
for seed in map(int, sys.argv[1:]):
    with tempfile.TemporaryDirectory() as tmp:
        case = phantom_case(seed, Path(tmp), 2.0)
        labels = load_cta(Path(tmp) / "labels.nii.gz", check_hu=False).array
        rig = nominal_poses(case.runs)
        X = patient_pose(case.true_poses["pa"], rig["pa"])
        reg = register_case(case.cta, case.runs, models=models)
        prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
        images = TTOImages(torch_renderer_for(reg.renderer), tto_views(prepared, {k: X @ rig[k] for k in rig}), Objective())
        views = [(v.name, v.vessels, v.detector) for v in images.views if images.vessel_term[v.name]]
        volume = reg.renderer.volume
        for where, P in (("truth", X), ("estimate", reg.registration.search.patient_pose),
                         ("result", reg.registration.patient_pose)):
            kept = opacified.read_opacified(volume, P, rig, views).kept_kji
            lab = labels[tuple(kept.T)]
            artery, vein = np.isin(lab, ARTERIES), np.isin(lab, VEINS)
            cells = [f"read {artery.sum()}/{vein.sum()}"]
            points = volume.centred_points(kept)
            for blur, shift in ((0.7, 0), (0.7, 3), (1.0, 3), (1.5, 3)):
                w = mlem_weights(points, P, rig, views, blur, shift_px=shift)
                k = w >= 0.05 * np.percentile(w, 90)
                cells.append(f"blur {blur} shift {shift}: {artery[k].sum()}/{vein[k].sum()}")
            print(seed, where, " | ".join(cells), flush=True)
