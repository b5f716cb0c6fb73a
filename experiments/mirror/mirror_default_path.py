"""The mirror test as a user meets it: each held-out phantom registered with ``register_case`` (the CTA and the two
runs, masks computed) as it is and with its CTA mirrored (the array flipped along the left-right axis, the header
kept: what a CTA whose header swaps the sides gives); per registration the carotid mPCD, the flags and the mirror
test's margin (``register/mirror.py``: the mirrored hypothesis's objective less the result's; below
``-MIRROR_LOSS_MARGIN`` the result fails).

    .venv/bin/python experiments/mirror/mirror_default_path.py --seeds 6010-6019 --doc experiments/mirror/default_path.md
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import parse_heldout_args  # noqa: E402

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.register import register_case  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.mirror import MIRROR_LOSS_MARGIN  # noqa: E402


def main() -> None:
    args, seeds = parse_heldout_args(__doc__.splitlines()[0], "6010-6019")
    models = load_models(runtime="torch")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            case = phantom_case(seed, Path(tmp) / str(seed), args.spacing_mm)
            axis = 2 - int(np.argmax(np.abs(case.cta.ijk_to_ras[0, :3]) / np.asarray(case.cta.spacing_mm)))
            for name, cta in (("correct", case.cta), ("mirrored", case.cta.like(np.ascontiguousarray(np.flip(case.cta.array, axis))))):
                reg = register_case(cta, case.runs, models=models)
                mirror = reg.registration.mirror
                row = {"seed": seed, "cta": name,
                       "mpcd_mm": [carotid_mpcd(reg.views[k].final_pose, case.true_poses[k], case.runs[k].detector,
                                                case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm for k in ("pa", "lat")],
                       "flags": [reg.views[k].quality.flag for k in ("pa", "lat")],
                       "margin": None if mirror is None else mirror.margin, "mirror_s": reg.runtimes_s.get("mirror"),
                       "total_s": reg.runtimes_s["total"]}
                rows.append(row)
                print(json.dumps(row, default=float), file=sys.stderr, flush=True)
    lines = [f"Fails below -{MIRROR_LOSS_MARGIN}.", "",
             "| seed | CTA | mPCD PA / LAT (mm) | flags | mirror margin | mirror test (s) |", "|---|---|---|---|---:|---:|"]
    for r in rows:
        margin = "not run" if r["margin"] is None else f"{r['margin']:+.3f}"
        lines.append(f"| {r['seed']} | {r['cta']} | {r['mpcd_mm'][0]:.1f} / {r['mpcd_mm'][1]:.1f} | {' / '.join(r['flags'])} | "
                     f"{margin} | {r['mirror_s'] or 0:.1f} |")
    for name in ("correct", "mirrored"):
        group = [r for r in rows if r["cta"] == name]
        failed = sum(r["flags"][0] == "failed" and r["margin"] is not None and r["margin"] < -MIRROR_LOSS_MARGIN for r in group)
        lines.append(f"\n{name}: {failed} of {len(group)} failed by the mirror test")
    text = "\n".join(lines)
    print(text)
    if args.doc:
        args.doc.write_text(text + "\n")
        args.doc.with_suffix(".json").write_text(json.dumps(rows, default=float, indent=1))


if __name__ == "__main__":
    main()
