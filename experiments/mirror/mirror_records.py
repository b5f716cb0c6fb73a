"""The mirror test's record (``registration.mirror`` without the plane) of chosen phantoms, as written or mirrored.

Each folder ``FOLDERS/SEED`` is a phantom as ``geopose phantom`` writes it; the CTA as written (``correct``) or with
its array flipped left-right (``mirrored``) is registered with ``register_case`` (the CTA and the two runs only). One
line per registration: the seed, the CTA, the record's numbers (both margins, the decision, the note).

    .venv/bin/python experiments/mirror/mirror_records.py /tmp/ph2 6011,6025,6027 mirrored
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from heldout import written_correct_and_mirrored  # noqa: E402  (also puts the library on the path, geopose before torch)

import torch  # noqa: E402

from geopose.nets import load_models  # noqa: E402
from geopose.register import pipeline  # noqa: E402


def main() -> None:
    torch.set_num_threads(2)
    models = load_models(runtime="torch")
    seeds, which = {int(s) for s in sys.argv[2].split(",")}, sys.argv[3]
    for seed, name, cta, runs in written_correct_and_mirrored(Path(sys.argv[1]), min(seeds), max(seeds)):
        if seed in seeds and name == which:
            record = pipeline.register_case(cta, runs, models=models).registration.mirror.as_dict()
            record.pop("plane")
            print(seed, name, json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in record.items()}),
                  flush=True)


if __name__ == "__main__":
    main()
