"""Data to calibrate the quality flag on: the default registration (the user's path: the CTA and the two
runs only) of validation phantoms and real-head cases, with every view's flag inputs and its outcome.

Writes one JSON line per case to ``--out`` (resumable: cases already there are skipped) and prints, per
view, the outcome (final carotid mPCD or, without arteries, rotation error) beside the flag's inputs.
Tune on validation seeds (6010-6029 and real-head seeds 3-5 by default), never on the benchmark's.

    python benchmarks/calibrate_quality.py --out /tmp/quality.jsonl --headsq ../shared/data/headsq/quarter_sidecar.mhd \\
        --ge-head ../shared/data/ge_head_ct_tilt
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "Logic"))

from geopose.bench.cases import ge_head_case, headsq_case, phantom_case, seed_range, training_seeds  # noqa: E402
from geopose.nets.predictors import load_models  # noqa: E402
from geopose.register.biplane import nominal_poses  # noqa: E402
from geopose.register.evaluate import evaluate_pose  # noqa: E402
from geopose.register.pipeline import register_case  # noqa: E402
from geopose.register.trust import stage_agreement  # noqa: E402
from geopose.resources import default_models_dir  # noqa: E402
import torch  # noqa: E402  after geopose, which sets OMP_WAIT_POLICY first


def view_rows(case, reg) -> list[dict]:
    """Per view: the flag's inputs and the outcome against the truth (DICOM angles' errors beside it)."""
    rig = nominal_poses(case.runs)
    rows = []
    for key, view in reg.views.items():
        run = case.runs[key]
        final = evaluate_pose(view.final_pose, case.true_poses[key], run.detector, run.angles.sod_mm, case.carotid_points_mm)
        dicom = evaluate_pose(rig[key], case.true_poses[key], run.detector, run.angles.sod_mm, case.carotid_points_mm)
        rotation, shift = stage_agreement(view.search_pose if view.search_pose is not None else view.refine.pose, view.final_pose)
        rows.append({
            "case": case.name, "view": key, "flag": view.quality.flag, "reasons": list(view.quality.reasons),
            "mncc": view.final_mncc, "silhouette_dice": view.silhouette_dice, "stage_rotation_deg": rotation,
            "stage_translation_mm": shift, **(view.evidence.as_dict() if view.evidence else {}),
            "chosen_start": reg.registration.chosen_start, "tto_objective": reg.registration.tto_objective,
            "vessel_evidence": reg.registration.vessel_evidence, "masks": reg.labels_source,
            "mirror": None if reg.registration.mirror is None else reg.registration.mirror.as_dict(),
            "mpcd_mm": final.get("mpcd_mm"), "rotation_error_deg": final["rotation_error_deg"],
            "source_distance_mm": final["source_distance_mm"], "dicom_rotation_error_deg": dicom["rotation_error_deg"],
            "dicom_source_distance_mm": dicom["source_distance_mm"], "dicom_mpcd_mm": dicom.get("mpcd_mm"),
        })
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="JSON-lines file (one line per case; resumable)")
    ap.add_argument("--seeds", type=seed_range, default=seed_range("6010-6029"), help="validation phantom seeds")
    ap.add_argument("--real-seeds", type=seed_range, default=seed_range("3-5"), help="real-head run seeds")
    ap.add_argument("--headsq", help="headsq quarter_sidecar.mhd")
    ap.add_argument("--ge-head", help="the GE head CT DICOM folder")
    ap.add_argument("--spacing-mm", type=float, default=2.0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    manifest = default_models_dir() / "manifest.json"
    clash = training_seeds(manifest) & set(args.seeds)
    if clash or set(args.seeds) & set(range(5000, 5040)):
        raise SystemExit("choose validation seeds: not the training seeds, not the benchmark's 5000-5039")
    done = {json.loads(line)[0]["case"] for line in args.out.read_text().splitlines()} if args.out.is_file() else set()
    models = load_models(default_models_dir(), runtime="torch", device="cpu")
    t0 = time.perf_counter()

    def cases(tmp: Path):
        for path, make in ((args.headsq, headsq_case), (args.ge_head, ge_head_case)):
            for arteries in (False, True):
                for seed in (args.real_seeds if path else []):
                    yield lambda path=path, make=make, seed=seed, arteries=arteries: make(path, seed=seed, arteries=arteries)
        for seed in args.seeds:
            yield lambda seed=seed: phantom_case(seed, tmp / str(seed), args.spacing_mm)

    with tempfile.TemporaryDirectory() as tmp:
        for make in cases(Path(tmp)):
            case = make()
            if case.name in done:
                continue
            rows = view_rows(case, register_case(case.cta, case.runs, models=models))
            with args.out.open("a") as f:
                f.write(json.dumps(rows) + "\n")
            for r in rows:
                print(f"{r['case']} {r['view']}: {r['flag']} mPCD {r['mpcd_mm']} rot {r['rotation_error_deg']:.1f} "
                      f"(DICOM {r['dicom_rotation_error_deg']:.1f}) vessel NCC {r.get('vessel_ncc')} mirror "
                      f"{r.get('mirror_margin')} mNCC {r['mncc']:.2f} Dice {r['silhouette_dice']:.2f} "
                      f"({(time.perf_counter() - t0) / 60:.1f} min)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
