"""What in the TTO's opacified vessel selection makes it drift from the truth on the default path? Each held-out
phantom's default TTO is started at the true pose (as the benchmark's drift row), masks computed from the CTA, and the
vessels the runs show opacified read there (``register/opacified.py``); in the oracle variants the selection then loses
the voxels of some phantom labels before the first step:

* ``computed``: the selection as read (the user's path);
* ``no veins`` / ``no extracranial veins`` / ``no intracranial veins``: the venous sinus label (cavernous sinuses,
  dural sinuses, jugular veins) removed everywhere / outside the cranium / inside it;
* ``no rim``: the voxels that are neither artery nor vein removed (partial volume round the arteries, bone);
* ``arteries only``: everything but the arteries removed.

One JSON line per phantom: the composition of the selection by label group, and per variant the TTO's end (carotid
mPCD PA / LAT, mm; rotation error, deg) and the voxels kept.

    .venv/bin/python experiments/vessel_mask/selection_oracle.py --seeds 6020-6031 --doc /tmp/selection_oracle.jsonl
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from heldout import parse_heldout_args  # noqa: E402

from geopose.bench.cases import phantom_case  # noqa: E402
from geopose.cta.io import load_cta  # noqa: E402

from geopose.metrics.measures import pose_error_components  # noqa: E402
from geopose.nets import load_models  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402
from geopose.register import opacified, register_case, tto  # noqa: E402
from geopose.register.biplane import nominal_poses, patient_pose  # noqa: E402
from geopose.register.engine import torch_renderer_for  # noqa: E402
from geopose.register.evaluate import carotid_mpcd  # noqa: E402
from geopose.register.tto import TTOSchedule, test_time_optimise, tto_views  # noqa: E402

ARTERIES = L.with_intracranial(L.ARTERY_LABELS)
VEINS = L.with_intracranial([L.VENOUS_SINUS])
#: Variant -> which selected voxels it drops, from their phantom labels.
DROPPED = {
    "computed": lambda lab: np.zeros(lab.shape, dtype=bool),
    "no veins": lambda lab: np.isin(lab, VEINS),
    "no extracranial veins": lambda lab: lab == L.VENOUS_SINUS,
    "no intracranial veins": lambda lab: lab == L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET,
    "no rim": lambda lab: ~np.isin(lab, ARTERIES + VEINS),
    "arteries only": lambda lab: ~np.isin(lab, ARTERIES),
}


class OracleRead:
    """``opacified.read_opacified`` as the TTO calls it, less the voxels whose label ``drop`` picks."""

    def __init__(self) -> None:
        self.labels: np.ndarray | None = None
        self.drop = DROPPED["computed"]
        self.composition: dict[str, int] = {}

    def __call__(self, volume, patient, rig, views, **kwargs):
        selection = opacified.read_opacified(volume, patient, rig, views, **kwargs)
        if selection is None or not selection.applied:
            return selection
        if self.labels.shape != selection.keep.shape:
            raise SystemExit("the oracle needs the vessel mask on the phantom's grid: use phantoms of 1 mm or coarser")
        lab = self.labels[tuple(selection.kept_kji.T)]
        self.composition = {"arteries": int(np.isin(lab, ARTERIES).sum()), "veins outside the cranium":
                            int((lab == L.VENOUS_SINUS).sum()), "veins inside the cranium":
                            int((lab == L.VENOUS_SINUS + L.INTRACRANIAL_OFFSET).sum()),
                            "other": int((~np.isin(lab, ARTERIES + VEINS)).sum())}
        kept = selection.kept_kji[~self.drop(lab)]
        subset = volume.with_vessels(kept)
        return opacified.VesselSelection(subset.mask("vessels"), selection.vessel_voxels, len(kept), True,
                                         selection.start, selection.iteration, selection.patient_pose, kept, subset)


def drift_rows(variants: dict[str, Callable[[OracleRead], None]], description: str, default_seeds: str,
               read: OracleRead | None = None) -> None:
    """One JSON line per held-out phantom (the command line of ``heldout.parse_heldout_args``): the default TTO started
    at the true pose once per variant, each variant's setter called on the oracle read before its run; per variant the
    TTO's end (carotid mPCD PA / LAT, mm; rotation error, deg), the voxels kept and the selection's composition;
    ``read``: the oracle read (default :class:`OracleRead`)."""
    models = load_models(runtime="torch")
    options = RegistrationOptions().replace(**{"tto.iterations": 0})
    read = read or OracleRead()
    tto.read_opacified = read  # the TTO reads through the oracle for this script only
    args, seeds = parse_heldout_args(description, default_seeds)
    out = open(args.doc, "w") if args.doc else sys.stdout
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            case = phantom_case(seed, Path(tmp), args.spacing_mm)
            read.labels = load_cta(Path(tmp) / "labels.nii.gz", check_hu=False).array
            rig = nominal_poses(case.runs)
            X = patient_pose(case.true_poses["pa"], rig["pa"])
            reg = register_case(case.cta, case.runs, models=models, options=options)
            prepared = {k: reg.views[k].prepared for k in ("pa", "lat")}
            row = {"case": case.name}
            for name, setup in variants.items():
                setup(read)
                result = test_time_optimise(torch_renderer_for(reg.renderer), tto_views(prepared, {k: X @ rig[k] for k in rig}),
                                            TTOSchedule(args.iterations), rig=rig)
                parts = pose_error_components(result.poses["pa"], case.true_poses["pa"])
                row[name] = {"drift_mm": [round(carotid_mpcd(result.poses[k], case.true_poses[k], case.runs[k].detector,
                                                             case.runs[k].angles.sod_mm, case.carotid_points_mm)[0].detector_mm, 3)
                                          for k in ("pa", "lat")],
                             "rotation_deg": round(float(np.hypot(parts["in_plane_rotation_deg"],
                                                                  parts["out_of_plane_rotation_deg"])), 3),
                             "kept": None if result.vessel_selection is None else result.vessel_selection.kept_voxels,
                             "selection": dict(read.composition)}
            row["selection"] = read.composition
            print(json.dumps(row), file=out, flush=True)


def main() -> None:
    def dropping(drop):
        def setup(read: OracleRead) -> None:
            read.drop = drop
        return setup

    drift_rows({name: dropping(drop) for name, drop in DROPPED.items()}, __doc__.splitlines()[0], "6020-6031")


if __name__ == "__main__":
    main()
