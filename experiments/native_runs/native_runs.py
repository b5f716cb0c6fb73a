"""Do runs archived native (radiographs with a Mask Subtraction Sequence) register as well as the same runs stored
subtracted? Each validation phantom is written twice by `geopose phantom` (same seed: the same subject, poses and
frames; once `--native-runs`) and registered as a user does (`register_files`: the CTA and the two runs, masks
computed); the truth only scores. One JSON line per seed and storage.

    .venv/bin/python experiments/native_runs/native_runs.py 6010-6019 --spacing-mm 1 > rows.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import geopose  # noqa: F401  (before torch)
from geopose.bench.cases import seed_range
from geopose.dsa import read_dsa
from geopose.phantom.cli import write_phantom
from geopose.register.cli import register_files


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seeds", type=seed_range)
    ap.add_argument("--spacing-mm", type=float, default=1.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for storage in ("subtracted", "native"):
                folder = Path(tmp) / f"{seed}_{storage}"
                write_phantom(seed, folder, spacing_mm=args.spacing_mm, native_runs=storage == "native")
                t0 = time.perf_counter()
                for key in ("pa", "lat"):
                    read_dsa(folder / f"dsa_{key}.dcm")
                read_s = time.perf_counter() - t0
                t0 = time.perf_counter()
                record = register_files(folder / "cta.nii.gz", folder / "dsa_pa.dcm", folder / "dsa_lat.dcm", folder / "out")
                row = {"seed": seed, "storage": storage, "seconds": round(time.perf_counter() - t0, 2),
                       "read_both_runs_s": round(read_s, 2),
                       "run_bytes": sum((folder / f"dsa_{k}.dcm").stat().st_size for k in ("pa", "lat"))}
                for key in ("pa", "lat"):
                    view = record["views"][key]
                    row[key] = {"mpcd_mm": view["truth"]["final"]["mpcd_mm"], "rotation_deg": view["truth"]["final"]["rotation_error_deg"],
                                "flag": view["quality"]["flag"]}
                print(json.dumps(row), flush=True)


if __name__ == "__main__":
    sys.exit(main())
