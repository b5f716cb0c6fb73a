"""The mirror test's two sides judged once more on vessels read again at each side's final pose and thinned by the
two-view emission fit (``experiments/vessel_mask/selection_fit/selection_mlem.py``): the tournament's lenient read
(2 px, 0.02), then the voxels whose MLEM weight reaches a share of the 90th percentile. As ``end_read.py``: each held-out
phantom registered as a user does, its CTA as given and mirrored; one JSON line per CTA: the product's margin and per
variant (margin, voxels kept by the result's read, by the mirrored hypothesis's).

    .venv/bin/python experiments/mirror/end_fit.py --seeds 6010-6012 6024-6029 > rows.jsonl
"""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "vessel_mask" / "selection_fit"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from end_read import mirror_ends  # noqa: E402
from selection_mlem import mlem_weights  # noqa: E402
from geopose.register import opacified as O  # noqa: E402
from geopose.register.biplane import patient_pose  # noqa: E402
from geopose.register.objective import pair_objective  # noqa: E402
from geopose.render.renderer import make_renderer  # noqa: E402

#: (MLEM blur px, share of the 90th percentile); None: the lenient read alone.
VARIANTS = [None, (0.7, 0.05), (1.0, 0.1), (0.7, 0.2)]


def judged(volume, poses, views, rig, objective, engine, fit):
    """The objective of ``poses`` on the vessels read at their patient pose (thinned by ``fit``), and the voxels kept."""
    X = patient_pose(poses["pa"], rig["pa"])
    images = [(k, views[k].tto_vessels, views[k].tto_detector) for k in views]
    sel = O.read_opacified(volume, X, rig, images)
    if sel is None or not sel.applied:
        return pair_objective(make_renderer(volume, engine, "cpu"), poses, views, objective), 0
    kept = sel.kept_kji
    if fit is not None:
        w = mlem_weights(volume.centred_points(kept), X, rig, [i for i in images if np.max(i[1]) > 0], fit[0])
        kept = kept[w >= fit[1] * np.percentile(w, 90)]
    judge = make_renderer(volume.with_vessels(kept), engine, "cpu")
    return pair_objective(judge, poses, views, objective), len(kept)


def main() -> None:
    for case, name, reg, work, res_poses, mvol, m, views, rig, objective, out in mirror_ends(__doc__.splitlines()[0]):
        row = {"case": case.name, "cta": name, "margin": reg.registration.mirror.margin}
        for fit in VARIANTS:
            a, ka = judged(work, res_poses, views, rig, objective, reg.renderer.engine, fit)
            b, kb = judged(mvol, m.poses, views, rig, objective, reg.renderer.engine, fit)
            row["lenient" if fit is None else f"fit {fit[0]}/{fit[1]}"] = (round(b - a, 4), ka, kb)
        print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
