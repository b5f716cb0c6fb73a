"""The result record (``result.json``): every matrix, trace, runtime and checksum
of a registration. Versioned: readers check ``schema`` and ``schema_version``."""

from __future__ import annotations

import datetime as _dt
import platform
from dataclasses import asdict
from typing import Any

import numpy as np

from .. import OPENMP_THREADS_SLEEP, __version__
from .. import contract as C
from ..dsa import DSARun
from ..geometry.detector import AP_REORIENT, carm_angles_from_params
from ..geometry.frames import pose_to_patient
from ..geometry.poses import params_from_pose, pose_from_carm_angles
from .continuation import CONTINUE_TURN_DEG, CONTINUED_START
from .results import CaseRegistration, ViewOutcome

SCHEMA = "geopose-result"
#: 19: ``registration.pairing`` also where the vessels are a given segmentation, with ``given_segmentation`` (a loose
#: fit is then doubtful, never failed); a note where the CTA is too coarse for the test.
#: 18: ``registration.pairing``: per view the vessel NCC at the TTO's result and with both images blurred, their gain
#: and whether the fit is too loose for one patient's CTA (``register/pairing.py``; null when not run).
#: 17: ``inputs.dsa_pa`` / ``inputs.dsa_lat`` hold ``subtraction`` where the run was archived native and subtracted by
#: its own Mask Subtraction Sequence (``dsa/subtraction.py``); the Slicer record names each run's node.
#: 16: ``registration.mirror`` adds ``short_loss`` and ``equal_effort_margin`` (the CTA as given through the mirrored
#: hypothesis's short fit from the same start; null where the result's margin already failed it),
#: ``equal_effort_fail_margin`` and ``sides_alike`` (the note was given).
#: 15: ``registration.vessel_images`` (per view, which of the run's vessel images the objective compared: the
#: bolus-weighted frames or the run's first half, and each one's NCC with the CTA's vessels at the networks' estimate;
#: ``register/vessel_image.py``).
#: 14: ``engine.finest_level_mm`` (the finest CTA level the renderers sample, ``register/engine.finest_level_mm``
#: unless the option ``work_spacing_mm`` set it), and that option's meaning: a bound on the level's voxels, no
#: longer a floor on each axis.
#: 13: ``engine.cta_render_grid_mm`` (the voxel size of the grid the CTA is rendered on: its own, or its block means
#: where it is finer than ``render.volume.RENDER_GRID_MM``) and the option ``estimate_voxel_per_pixel``.
#: 12: ``registration.tto_stopped_behind`` (a finalist of the TTO's tournament stopped after the coarse steps: how
#: far it was behind the leader there, by one objective).
#: 11: ``work``: per stage the renders, rays and ray points (samples x channels) both kernels did, and the
#: stage's ns per point (``render/work.py``): what a stage's time is made of.
#: 10: ``options`` is the options tree (``options.py``): the engine's settings at the top, each stage's in its
#: group (``refine``, ``search``, ``tto``, ``objective``); ``options.tto.px`` was ``options.tto_px``,
#: ``options.tto.iterations`` ``options.iterations``, ``options.refine.steps`` ``options.refine_steps``,
#: ``options.search.enabled`` ``options.search``.
#: 9: each view's ``evidence`` (the objective's terms at the final pose, ``register/evidence.py``),
#: ``registration.vessel_evidence``, ``registration.bound`` (without vessel evidence, the move from the
#: DICOM angles asked for and kept, ``register/bound.py``; null otherwise) and ``registration.mirror``
#: (the result against the CTA mirrored left-right, ``register/mirror.py``; null when not run),
#: ``registration.kept_learned`` (why the networks' estimate was kept over the TTO's result; null: it was not).
#: 8: ``registration.similarity_search`` (the search after biplane greedy Refine: start and end mNCC and
#: patient pose, the moves kept, the poses scored; null when it did not run) and the views' ``search``
#: stage pose.
#: 7: each of ``tto_axis_searches`` adds ``rotation_per_rad`` and ``shift_mm_per_rad``: the direction it
#: searched along (the turn about the common axis with the other parameters' compensation,
#: ``axis_search.valley_turn``).
#: 6: ``registration.tto_vessel_selection`` (the opacified vessels the TTO's vessel term kept after its
#: coarse steps: voxels kept of all, where it was read, the runs that kept them; ``register/opacified.py``),
#: null without one.
#: 5: ``registration.tto_ranking_loss`` and ``tto_stopped_at`` (the TTO's tournament of starts: each
#: start's full-size loss after the coarse steps and the first common-axis search; the iteration
#: the ones not kept stopped at).
#: 4: ``tto_axis_searches`` (the TTO's turns about the biplane common axis: iteration, turns in
#: deg, losses, the turn chosen). 3: ``engine`` (backend, renderer, device, render sizes, CTA
#: levels), ``notes``, the options of ``geopose.options``; ``carm`` angles keep DICOM's signs and
#: views name their pixel axes (``patient_orientation``, docs/conventions.md section 7).
#: 2: ``view_logits`` are mirror-averaged; 1: single-image logits.
SCHEMA_VERSION = 19

__all__ = ["SCHEMA", "SCHEMA_VERSION", "build_record", "library_versions", "patient_orientation"]

#: A pixel axis is named by every patient axis it makes at most about 67.5 deg with (cosine >= 0.38),
#: the nearest first, as DICOM PatientOrientation (0020,0020) does ("L", "LP", ...).
ORIENTATION_MIN_COSINE = 0.38
#: Letters of the patient's RAS axes: (negative, positive) direction.
_AXIS_LETTERS = (("L", "R"), ("P", "A"), ("F", "H"))


def _m(pose: np.ndarray) -> list:
    return np.asarray(pose, dtype=np.float64).reshape(4, 4).tolist()


def library_versions() -> dict[str, str]:
    import SimpleITK
    import onnxruntime
    import pydicom

    try:
        import torch

        torch_version = torch.__version__
    except ImportError:
        torch_version = "not installed"
    return {
        "geopose": __version__,
        "python": platform.python_version(),
        "torch": torch_version,
        "numpy": np.__version__,
        "SimpleITK": SimpleITK.Version_VersionString(),
        "onnxruntime": onnxruntime.__version__,
        "pydicom": pydicom.__version__,
        "openmp_idle_threads": "sleep" if OPENMP_THREADS_SLEEP else "spin (see the notes)",
    }


def _pose_entry(case: CaseRegistration, pose: Any) -> dict:
    centred = np.asarray(pose, dtype=np.float64).reshape(4, 4)
    return {
        "pose_centred": centred.tolist(),
        "pose_ras": pose_to_patient(centred, case.cta.ijk_to_ras, case.cta.shape_ijk, "RAS").tolist(),
    }


def patient_orientation(pose: np.ndarray) -> list[str]:
    """DICOM PatientOrientation of a view's pixels for a camera-to-world pose (world axes RAS,
    e.g. the centred CTA frame): the patient direction of increasing column, then of increasing
    row. A PA is ``["L", "F"]``, an RAO lateral ``["A", "F"]``, an LAO lateral ``["P", "F"]``
    (docs/conventions.md, section 7)."""
    m = np.asarray(pose, dtype=np.float64)[:3, :3] @ AP_REORIENT[:3, :3]
    out = []
    for axis in (-m[:, 0], -m[:, 1]):  # columns grow towards camera -x, rows towards camera -y
        order = np.argsort(-np.abs(axis))
        out.append("".join(_AXIS_LETTERS[a][int(axis[a] > 0)] for a in order if abs(axis[a]) >= ORIENTATION_MIN_COSINE))
    return out


def _view_entry(case: CaseRegistration, v: ViewOutcome, run: DSARun) -> dict:
    r, t = params_from_pose(v.final_pose)
    angles = carm_angles_from_params(r, t, sid_mm=run.detector.sdd_mm)
    entry = {
        "role": v.prepared.view_role,
        "view_label": v.init.view,
        "view_name": C.VIEW_NAMES[v.init.view],
        "view_logits": np.asarray(v.init.logits, dtype=np.float64).reshape(-1).tolist(),
        "view_logits_doc": "(LAT-, PA, LAT+) logits of the MAP averaged with its left-right mirror's (nets.mirror_averaged_logits)",
        **_pose_entry(case, v.final_pose),
        "euler_zyx_rad": r.tolist(),
        "translation_mm": t.tolist(),
        "carm": asdict(angles),
        "carm_doc": "equivalent positioner angles (deg) and distances (mm) about the centred CTA frame's origin",
        "patient_orientation": patient_orientation(v.final_pose),
        "patient_orientation_from_angles": patient_orientation(pose_from_carm_angles(run.angles)),
        "patient_orientation_doc": "patient direction of increasing column, then of increasing row (DICOM PatientOrientation "
        "letters), of the registered pose and of the pose the run's positioner angles imply (docs/conventions.md, section 7); "
        "a disagreement means the image is mirrored against its angles or the registration picked the other side",
        "acquisition": {
            "primary_deg": run.angles.primary_deg,
            "secondary_deg": run.angles.secondary_deg,
            "sid_mm": run.angles.sid_mm,
            "sod_mm": run.angles.sod_mm,
            "detector": asdict(run.detector),
            "frames": int(run.frames.shape[0]),
        },
        "stages": {name: _pose_entry(case, p) for name, p in v.stage_poses.items()},
        "init": {"pose_canonical": _m(v.init.pose_canonical)},
        "refinement": {
            "start_mncc": v.refine.start_mncc,
            "final_mncc": v.refine.mncc,
            "accepted": v.refine.accepted,
            "proposals": [
                {"mncc": p.mncc, "accepted": p.accepted, "pose_centred": _m(p.pose)} for p in v.refine.proposals
            ],
        },
        "final_mncc": v.final_mncc,
        "final_mncc_doc": "mNCC of the final DRR against the TTO target (acquisition SDD)",
        "silhouette_dice": v.silhouette_dice,
        "quality": v.quality.as_dict(),
        "evidence": None if v.evidence is None else v.evidence.as_dict(),
    }
    if case.tto is not None:
        entry["tto"] = {"best_iteration": case.tto.best_iteration[v.key], "best_mncc": case.tto.best_mncc[v.key]}
    return entry


def _search_entry(case: CaseRegistration) -> dict | None:
    """The similarity search after biplane greedy Refine, or None when it did not run."""
    search = case.registration.search
    if search is None:
        return None
    return {"start_mncc": search.start_mncc, "mncc": search.mncc, "start_patient_pose_centred": _m(search.start_pose),
            "patient_pose_centred": _m(search.patient_pose), "evaluations": search.evaluations,
            "moves": [{"parameter": name, "step": step} for name, step in search.moves],
            "doc": "mNCC: the views' mean in the model geometry at the finest step's image size "
            "(options.search.schedule); steps in mm (shift) or deg (turn)"}


def _vessel_selection(case: CaseRegistration) -> dict | None:
    """The TTO's reading of the opacified vessels and the runs that compared them alone, or None."""
    selection = case.registration.vessel_selection
    if selection is None:
        return None
    return selection.summary() | {"runs": [k for k, r in case.registration.tto_runs.items() if r.vessel_selection is not None]}


def _with_subtractions(inputs: dict[str, Any], runs: dict[str, DSARun]) -> dict[str, Any]:
    """``inputs`` with, for each run read native and subtracted by its own header, how (``dsa_<key>.subtraction``)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in inputs.items()}
    for key, run in runs.items():
        if "subtraction" in run.metadata:
            out.setdefault(f"dsa_{key}", {})["subtraction"] = run.metadata["subtraction"]
    return out


def build_record(
    case: CaseRegistration,
    runs: dict[str, DSARun],
    *,
    inputs: dict[str, Any] | None = None,
    truth_metrics: dict[str, dict] | None = None,
) -> dict:
    """JSON-ready record of a :class:`CaseRegistration` (see the module doc)."""
    cal = case.calibration
    record: dict[str, Any] = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "frames_doc": "pose_centred: camera-to-world 4x4 in the centred native CTA frame (RAS axes, origin at the "
        "voxel-grid centre, mm); pose_ras: camera-to-RAS 4x4 in the CTA's patient frame; camera: source at origin, "
        "detector at z = SDD, AP reorientation applied (docs/conventions.md 1-2)",
        "inputs": _with_subtractions(inputs or {}, runs),
        "environment": library_versions(),
        "options": case.options.as_dict(),
        "engine": case.engine,
        "notes": list(case.notes),
        "labels_source": case.labels_source,
        "cta": {
            "shape_ijk": list(case.cta.shape_ijk),
            "spacing_mm": list(case.cta.spacing_mm),
            "ijk_to_ras": case.cta.ijk_to_ras.tolist(),
            "centred_to_ras": case.cta.centred_to_ras.tolist(),
        },
        "registration": {
            "mode": case.registration.mode,
            "mode_doc": "biplane-rigid: one patient pose X for both views, camera poses X @ A_v with A_v from each run's "
            "DICOM angles (nominal_pose_centred); independent views: each view on its own (the published pipeline)",
            "tto_start": case.registration.chosen_start,
            "tto_start_doc": "the start the result came from: every distinct start runs the TTO's coarse steps, the DICOM "
            "angles' run and the best other by the full-size loss there are the finalists, one judged there by one "
            "objective more than options.tto.stop_behind behind the other stops (tto_stopped_behind), the others run to "
            "the end, the lower objective wins, the DICOM angles' within a tie of 1e-3 (without a TTO: the best start); "
            f"\"{CONTINUED_START}\": a result that turned more than {CONTINUE_TURN_DEG:g} deg from its start ran once "
            "more from where it ended, and that run won, the finalists and it judged by the vessels it read (register/continuation.py)",
            "start_objective": case.registration.starts,
            "tto_objective": case.registration.tto_objective,
            "tto_ranking_loss": {k: r.ranking_loss for k, r in case.registration.tto_runs.items() if r.ranking_loss is not None},
            "tto_stopped_at": {k: r.stopped_at for k, r in case.registration.tto_runs.items() if r.stopped_at is not None},
            "tto_stopped_behind": {k: r.behind for k, r in case.registration.tto_runs.items() if r.behind is not None},
            "tto_vessel_selection": _vessel_selection(case),
            "patient_pose_centred": None if case.registration.patient_pose is None else _m(case.registration.patient_pose),
            "nominal_pose_centred": {k: _m(A) for k, A in case.registration.rig.items()},
            "checks": case.registration.checks,
            "vessel_evidence": case.registration.vessel_evidence,
            "bound": None if case.registration.bound is None else case.registration.bound.as_dict(),
            "mirror": None if case.registration.mirror is None else case.registration.mirror.as_dict(),
            "pairing": None if case.registration.pairing is None else case.registration.pairing.as_dict(),
            "kept_learned": case.registration.kept_learned or None,
            "refine_start": case.registration.refine_start,
            "refine_start_doc": "biplane-rigid: greedy Refine ran from every combination of a rotation and an isocentre "
            "of the fused Init and each view's Init; the end with the highest mean mNCC (refine_start_mncc) was kept",
            "refine_start_mncc": case.registration.refine_starts,
            "similarity_search": _search_entry(case),
            "vessel_images": {k: {"used": c.used, "ncc_at_estimate": c.ncc} for k, c in case.registration.vessel_images.items()},
            "vessel_images_doc": "per view, the vessel image the objective compared: bolus (the frames weighted by the run's "
            "bolus curve) or early (the mean of the run's first half, used where its NCC with the CTA's vessels rendered at "
            "the networks' estimate beats the bolus image's by register/vessel_image.EARLY_IMAGE_LEAD); empty: not chosen "
            "(no vessels in the CTA, or independent views)",
        },
        "calibration": {
            "calibration_pose": _m(cal.calibration_pose),
            "predicted_canonical": _m(cal.predicted_canonical),
            "frame_transfer": _m(cal.frame_transfer),
            "frame_transfer_doc": "canonical -> native (centred frames): T_native = frame_transfer @ T_canonical",
        },
        "views": {key: _view_entry(case, v, runs[key]) for key, v in case.views.items()},
        "runtimes_s": case.runtimes_s,
        "work": case.work,
    }
    if case.tto is not None:
        record["tto_trace"] = [
            {"iteration": e["iteration"], "loss": e["loss"], "views": {k: {"mncc": d["mncc"], "dice_loss": d["dice_loss"]} for k, d in e["views"].items()}}
            for e in case.tto.trace
        ]
        record["tto_axis_searches"] = case.tto.axis_searches
    if truth_metrics:
        for key, metrics in truth_metrics.items():
            record["views"][key]["truth"] = metrics
    return record

