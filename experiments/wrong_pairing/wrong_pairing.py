"""A wrong pairing on the user's path: one subject's CTA registered with another subject's two runs.

For each seed s in the list, ``geopose register`` runs (as a user types it) with the CTA of s and the runs of the
next seed in the list (crossed), and with the CTA and runs of s (correct). The CTA is given through a link in a folder
of its own (the registration still finds its phantom truth, through the link, and scores against it: meaningless for
a crossed pair, whose rows leave it out). One JSON row per registration: the flags, their reasons, the objective's
terms per view and the mirror test's margins.

    python wrong_pairing.py PHANTOM_DIR OUT_DIR ROWS.jsonl SEED [SEED ...]
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def register(cta: Path, runs: Path, out: Path) -> dict:
    """``geopose register`` with the CTA ``cta`` and the runs in the folder ``runs``; its result record."""
    if not (out / "result.json").exists():
        link = out.parent / f"{out.name}-cta"
        link.mkdir(parents=True, exist_ok=True)
        (link / "cta.nii.gz").unlink(missing_ok=True)
        (link / "cta.nii.gz").symlink_to(cta)
        cmd = [sys.executable, "-c", "import sys; from geopose.cli import main; sys.exit(main(sys.argv[1:]))", "register",
               "--cta", str(link / "cta.nii.gz"), "--dsa-pa", str(runs / "dsa_pa.dcm"), "--dsa-lat", str(runs / "dsa_lat.dcm"),
               "--out", str(out)]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads((out / "result.json").read_text())


def row(record: dict, cta_seed: int, runs_seed: int) -> dict:
    reg, views = record["registration"], record["views"]
    mirror = reg.get("mirror") or {}
    return {
        "cta": cta_seed, "runs": runs_seed, "crossed": cta_seed != runs_seed,
        "flags": {v: views[v]["quality"]["flag"] for v in views},
        "reasons": {v: views[v]["quality"]["reasons"] for v in views},
        "evidence": {v: views[v]["evidence"] for v in views},
        "final_mncc": {v: views[v]["final_mncc"] for v in views},
        "dice": {v: views[v]["silhouette_dice"] for v in views},
        "mirror_margin": mirror.get("margin"), "equal_effort_margin": mirror.get("equal_effort_margin"),
        "loss": mirror.get("loss"), "start_objective": reg.get("start_objective"),
        "view_disagreement_mm": reg.get("checks", {}).get("view_disagreement_mm"),
        "total_s": record["runtimes_s"]["total"],
        "mpcd_mm": None if cta_seed != runs_seed else {v: views[v]["truth"]["final"]["mpcd_mm"] for v in views if "truth" in views[v]},
    }


def main(argv: list[str]) -> None:
    phantoms, out, rows_path, seeds = Path(argv[0]), Path(argv[1]), Path(argv[2]), [int(s) for s in argv[3:]]
    done = set()
    if rows_path.exists():
        done = {(r["cta"], r["runs"]) for r in map(json.loads, rows_path.read_text().splitlines())}
    for i, s in enumerate(seeds):
        for runs_seed in (seeds[(i + 1) % len(seeds)], s):
            if (s, runs_seed) in done:
                continue
            record = register(phantoms / str(s) / "cta.nii.gz", phantoms / str(runs_seed), out / f"{s}_{runs_seed}")
            with rows_path.open("a") as f:
                f.write(json.dumps(row(record, s, runs_seed)) + "\n")
            r = row(record, s, runs_seed)
            print(s, runs_seed, r["flags"], {v: round(e["vessel_ncc"], 3) for v, e in r["evidence"].items()},
                  r["mirror_margin"], flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
