"""Can the mirror test score at half size throughout? Its short TTO already steps at half size, but it scores its
start, its common-axis search and its last pose at full size, and both sides are judged at full size
(``register/mirror.py``). Each held-out phantom is registered with ``register_case`` (the CTA and the two runs,
masks computed) as it is and with its CTA mirrored (the array flipped along the left-right axis, the header kept);
in every registration the mirror test runs twice on the same tournament: as the product runs it, and with every
score of the test (the TTO's full-size scores and the judge) on the half-size images, the same objective (the
fitted silhouette). One JSON line per registration: both margins and both tests' seconds.

    .venv/bin/python experiments/mirror/half_size_judge.py --seeds 6010-6029 --doc experiments/mirror/half_size_judge.jsonl
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import heldout_phantoms  # noqa: E402

from geopose.images import resize_bilinear  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import mirror, pipeline, register_case, tto  # noqa: E402
from geopose.register.objective import pair_objective, view_terms  # noqa: E402

HALF = {"on": False}


def half_loss(self, name, pose, size):
    """``TTOImages.loss`` whose full-size scores use the half-size images (the objective unchanged) while HALF is on."""
    import torch

    if not (HALF["on"] and size == "full"):
        return ORIGINAL_LOSS(self, name, pose, size)
    target, mask, vessels, det, drr = self.levels[name, "half"]
    img = drr(pose, detector=det, channels=self.channels)
    return view_terms(img[0, 0], img[0, 1], img[0, 2], target[0, 0], mask[0, 0], vessels[0, 0], self.objective,
                      coarse=False, vessel_term=self.vessel_term[name], xp=torch)


def half_views(views):
    """The prepared runs with their TTO images on the half-size detector (as ``tto._half`` makes them)."""
    out = {}
    for key, v in views.items():
        det = v.tto_detector.resized(max(16, v.tto_detector.rows // 2), max(16, v.tto_detector.cols // 2))
        image, vessels = resize_bilinear(np.stack((v.tto_image, v.tto_vessels)).astype(np.float32), det.shape)
        mask = resize_bilinear((v.tto_mask > 0).astype(np.float32)[None], det.shape)[0] > 0.5
        out[key] = dataclasses.replace(v, tto_image=image, tto_vessels=vessels, tto_mask=mask.astype(v.tto_mask.dtype),
                                       tto_detector=det)
    return out


@contextmanager
def half_size():
    HALF["on"] = True
    mirror.pair_objective = lambda judge, poses, views, objective: pair_objective(judge, poses, half_views(views), objective)
    try:
        yield
    finally:
        HALF["on"] = False
        mirror.pair_objective = pair_objective


ORIGINAL_LOSS = tto.TTOImages.loss
ORIGINAL_TEST = pipeline.mirror_test
SEEN: dict = {}


def both_tests(*args, **kwargs):
    """The product's mirror test (returned), and the half-size one beside it (kept in SEEN)."""
    t = time.perf_counter()
    product = ORIGINAL_TEST(*args, **kwargs)
    SEEN["product_s"] = time.perf_counter() - t
    t = time.perf_counter()
    with half_size():
        half = ORIGINAL_TEST(*args, **kwargs)
    SEEN["half_s"] = time.perf_counter() - t
    SEEN["product"], SEEN["half"] = product.margin, half.margin
    return product


def main() -> None:
    tto.TTOImages.loss = half_loss
    pipeline.mirror_test = both_tests
    models = load_models(runtime="torch")
    for _, case, out in heldout_phantoms(__doc__.splitlines()[0], "6010-6029"):
        axis = 2 - int(np.argmax(np.abs(case.cta.ijk_to_ras[0, :3]) / np.asarray(case.cta.spacing_mm)))
        for name, cta in (("correct", case.cta), ("mirrored", case.cta.like(np.ascontiguousarray(np.flip(case.cta.array, axis))))):
            SEEN.clear()
            register_case(cta, case.runs, models=models)
            row = {"seed": int(case.name.rsplit("-", 1)[1]), "cta": name,
                   **{k: round(v, 4) for k, v in SEEN.items()}}
            print(json.dumps(row), file=out, flush=True)


if __name__ == "__main__":
    main()
