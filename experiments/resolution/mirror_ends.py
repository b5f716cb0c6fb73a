"""Why does the mirror test pass two mirrored 1 mm CTAs (6011, 6027) with a margin of +0.063? Each is registered
mirrored and as written (``register_case``, CTA and runs only, from the phantom folders of ``resolution.py``); per
registration the mirror test's two judged objectives (the result's and the mirrored hypothesis's after its short TTO)
and the tournament's objectives. One line per seed.

    .venv/bin/python experiments/resolution/mirror_ends.py /tmp/ph1 6011 6027
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import flipped_left_right  # noqa: E402  (also puts the library on the path, geopose before torch)

import torch  # noqa: E402

from geopose.cta.io import load_cta  # noqa: E402
from geopose.dsa.readers import read_dsa  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402


def main() -> None:
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    folders = Path(sys.argv[1])
    for seed in sys.argv[2:]:
        cta = load_cta(folders / seed / "cta.nii.gz")
        runs = {k: read_dsa(folders / seed / f"dsa_{k}.dcm") for k in ("pa", "lat")}
        out = {}
        for name, c in (("mirrored", flipped_left_right(cta)), ("correct", cta)):
            r = register_case(c, runs, models=models).registration
            out[name] = {"result_loss": round(r.mirror.loss, 4), "hypothesis_loss": round(r.mirror.mirrored_loss, 4),
                         "tto_objective": {k: round(v, 4) for k, v in r.tto_objective.items()}, "chosen": r.chosen_start}
        print(seed, json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
