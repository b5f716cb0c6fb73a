"""Why does the mirror test pass two mirrored 1 mm CTAs (6011, 6027) with a margin of +0.063? Each is registered
mirrored and as written (``register_case``, CTA and runs only, from the phantom folders of ``resolution.py``); per
registration the mirror test's two judged objectives (the result's and the mirrored hypothesis's after its short TTO)
and the tournament's objectives. One line per seed.

    .venv/bin/python experiments/resolution/mirror_ends.py /tmp/ph1 6011 6027
"""
import sys, json
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import heldout  # noqa: F401  (the library on the path, geopose before torch)
import numpy as np
import geopose
from geopose.register.pipeline import register_case
from geopose.cta.io import load_cta
from geopose.dsa.readers import read_dsa
from geopose.nets import load_models
import torch
torch.set_num_threads(2)
models = load_models(runtime="torch")
for seed in sys.argv[2:]:
    d = f"{sys.argv[1]}/{seed}"
    cta = load_cta(f"{d}/cta.nii.gz")
    runs = {"pa": read_dsa(f"{d}/dsa_pa.dcm"), "lat": read_dsa(f"{d}/dsa_lat.dcm")}
    axis = 2 - int(np.argmax(np.abs(cta.ijk_to_ras[0, :3]) / np.asarray(cta.spacing_mm)))
    out = {}
    for name, c in (("mirrored", cta.like(np.ascontiguousarray(np.flip(cta.array, axis)))), ("correct", cta)):
        r = register_case(c, runs, models=models).registration
        out[name] = {"result_loss": round(r.mirror.loss, 4), "hypothesis_loss": round(r.mirror.mirrored_loss, 4),
                     "tto_objective": {k: round(v, 4) for k, v in r.tto_objective.items()}, "chosen": r.chosen_start}
    print(seed, json.dumps(out), flush=True)
