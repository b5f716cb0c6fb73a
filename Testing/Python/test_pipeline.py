"""The whole registration (``pipeline.register_case``) with ground-truth oracles in place of trained networks.

A phantom case (2 mm, written and read back through the real file formats) is
registered with an oracle Init that answers the true canonical poses, so the
calibration algebra, the greedy gate and the test-time optimisation are tested
against known answers without any trained weights; a bad Init falls back to the
DICOM angles, one view's Init alone is a start, and on weak image evidence the
networks' estimate is kept; the published independent-views pipeline is registered the same way.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from register_helpers import ORACLE_RENDER_PX, OracleInit, OracleRefine, _perturb, _read_phantom

from geopose import contract as C
from geopose.cta import load_cta
from geopose.geometry import isopose
from geopose.nets import ModelSet
from geopose.options import RegistrationOptions, SearchOptions
from geopose.phantom import labels as L
from geopose.register import TTOSchedule, register_case
from geopose.register.continuation import CONTINUED_START
from geopose.register.evaluate import evaluate_pose, load_truth, truth_metrics
from geopose.register.objective import objective_value
from geopose.register.record import SCHEMA_VERSION, build_record
from geopose.register.report import write_overlays
from geopose.render.renderer import make_renderer


#: mPCD (mm at the detector) the TTO must reach on the phantom's simulated DSA MAP (see test_oracle_registration_...).
TTO_ORACLE_MPCD_MM = 5.0


def oracle_models(init: OracleInit, refine: OracleRefine) -> ModelSet:
    return ModelSet(init, refine, render_px=ORACLE_RENDER_PX, runtime="torch")


def test_oracle_registration_calibration_greedy_and_tto(phantom_case):
    case = phantom_case
    N, true, cta, runs = _read_phantom(case)
    start = {k: _perturb(true[k]) for k in true}
    t_cal = isopose(C.VIEW_PA)
    # A perfect Init: canonical poses N @ T for the calibration DRR and for each view.
    init = OracleInit([N @ t_cal, N @ start["pa"], N @ start["lat"]])
    refine = OracleRefine([])  # identity residuals: no proposal can strictly improve
    stages = []
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    result = register_case(
        cta, runs, models=oracle_models(init, refine), segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)),
        options=RegistrationOptions(backend="torch", device="cpu", tto=TTOSchedule(px=128)),
        progress=lambda stage, f, msg: stages.append(stage), preliminary=stages.append,
    )
    # The networks' estimate (the searched pose) was handed over once, before the TTO began, as the record gives it.
    handed = [s for s in stages if not isinstance(s, str)]
    assert len(handed) == 1 and handed[0].stage == "estimate"
    assert "search" in stages[:stages.index(handed[0])] and "tto" not in stages[:stages.index(handed[0])]
    assert "tto" in stages[stages.index(handed[0]):]
    for key in ("pa", "lat"):
        np.testing.assert_array_equal(handed[0].poses[key], result.views[key].stage_poses["search"])
    assert 0.0 < handed[0].elapsed_s < result.runtimes_s["total"]
    # Calibration recovers the canonical->native transfer exactly (it is inverse(N)); the
    # calibration image is the min-max DRR in the model geometry, rendered at the models' size.
    np.testing.assert_allclose(result.calibration.frame_transfer, np.linalg.inv(N), atol=1e-6)
    assert init.images[0].shape == (1, 1, C.MODEL_DETECTOR_PX, C.MODEL_DETECTOR_PX)
    assert init.images[0].min() == 0.0 and init.images[0].max() == 1.0
    for key in ("pa", "lat"):
        view = result.views[key]
        np.testing.assert_allclose(view.init.pose_native, start[key], atol=1e-6)
        # Identity proposals never strictly improve mNCC: the proposal and its half-size retry, both
        # rejected. The refined pose is one of the starts, all combinations of the views' patient poses
        # (equal up to the DICOM angles' stored precision).
        assert len(view.refine.proposals) == 2 and not any(p.accepted for p in view.refine.proposals)
        np.testing.assert_allclose(view.refine.pose[:3, :3], start[key][:3, :3], atol=1e-3)
        np.testing.assert_allclose(view.refine.pose[:3, 3], start[key][:3, 3], atol=0.5)
    assert refine.answered == 2 * 9  # both views once from each of the nine combined starts
    assert result.registration.refine_start in result.registration.refine_starts
    assert {"prepare", "calibration", "init", "refine", "search", "tto", "done"} <= {s for s in stages if isinstance(s, str)}
    assert result.engine["render_px"] == ORACLE_RENDER_PX
    metrics = truth_metrics(result, runs, load_truth(case / "cta.nii.gz"))
    for key in ("pa", "lat"):
        before, after = metrics[key]["init"], metrics[key]["final"]
        assert before["mpcd_mm"] > 3.0, before
        # On the phantom's simulated MAPs the GeoReg objective's own optimum lies 1-4.5 mm from
        # the truth, so this checks a large gain and <= TTO_ORACLE_MPCD_MM; the optimiser itself
        # reaches <= 1 mm on a consistent target (next test).
        assert after["mpcd_mm"] <= TTO_ORACLE_MPCD_MM, (key, before["mpcd_mm"], after["mpcd_mm"])
        assert after["mpcd_mm"] < 0.6 * before["mpcd_mm"] or after["mpcd_mm"] <= 1.0
        assert after["rotation_error_deg"] < before["rotation_error_deg"]
    record = build_record(result, runs, truth_metrics=metrics)
    assert record["schema_version"] == SCHEMA_VERSION
    tto_work = record["work"]["tto"]
    assert tto_work["renders"] > 0 and tto_work["ray_points"] > tto_work["rays"] > 0 and tto_work["ns_per_point"] > 0
    # The similarity search moved the refined patient pose to a higher mNCC and nearer the truth.
    search = record["registration"]["similarity_search"]
    assert search["mncc"] > search["start_mncc"] and search["moves"] and search["evaluations"] > 30
    for key in ("pa", "lat"):
        assert metrics[key]["search"]["mpcd_mm"] < metrics[key]["refine"]["mpcd_mm"], (key, metrics[key])
    json.dumps(record)  # JSON-ready
    pa = record["views"]["pa"]
    assert np.allclose(np.asarray(pa["pose_ras"]), cta.centred_to_ras @ np.asarray(pa["pose_centred"]))
    assert len(record["tto_trace"]) == TTOSchedule.iterations + 1
    assert [s["iteration"] for s in record["tto_axis_searches"]] == sorted(TTOSchedule().axis_search_iterations())
    assert all(len(s["rotation_per_rad"]) == 3 and len(s["shift_mm_per_rad"]) == 3 for s in record["tto_axis_searches"])
    assert pa["quality"]["flag"] in ("ok", "doubtful", "failed")
    assert record["engine"]["backend"] == "torch" and record["options"]["tto"]["px"] == 128
    # Overlays: one PNG per view, three stages side by side, vessels drawn in colour.
    pngs = write_overlays(result, case / "overlays", load_truth(case / "cta.nii.gz").carotid_points_mm)
    assert [p.name for p in pngs] == ["overlay_pa.png", "overlay_lat.png"]
    rgb = np.asarray(Image.open(pngs[0]))
    assert rgb.shape[1] > 3 * rgb.shape[0] * 0.9  # three panels
    red = (rgb[..., 0] > 200) & (rgb[..., 1] < 120)
    assert red.sum() > 100  # the projected vessels


class SideSwappedInit(OracleInit):
    """An oracle Init whose view logits read the other lateral side than the one it is told."""

    def predict(self, image, is_lateral=None, mirror=True, view=None):
        pose, label, _ = super().predict(image, is_lateral, mirror, view)
        read = 2 - label if bool(np.asarray(is_lateral).reshape(-1)[0]) else label
        return pose, label, np.eye(3)[read]


def test_a_bad_init_falls_back_to_the_dicom_angles_and_is_flagged(phantom_case):
    """Init 20 deg / 60 mm off, reading the lateral on the wrong side: the DICOM-angle pose scores
    best of the candidate starts, the TTO runs from it and from the one distinct learned start (which,
    far behind after the coarse steps, stops there), the result comes from the DICOM angles' run (run on from where
    it ended) and is no worse than that start by the same objective, and the lateral view carries the side doubt."""
    case = phantom_case
    N, true, cta, runs = _read_phantom(case)
    far = {k: _perturb(true[k], (12.0, -10.0, 12.0), (40.0, -30.0, 30.0)) for k in true}
    init = SideSwappedInit([N @ isopose(C.VIEW_PA), N @ far["pa"], N @ far["lat"]])
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    result = register_case(
        cta, runs, models=oracle_models(init, OracleRefine([])), segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)),
        options=RegistrationOptions(backend="torch", device="cpu", tto=TTOSchedule(iterations=6, px=96),
                                    search=SearchOptions(enabled=False)),
    )
    registration = result.registration
    assert registration.search is None and "search" not in result.views["pa"].stage_poses
    assert set(registration.starts) == {"DICOM angles", "Init", "Init PA", "Init LAT", "Refine"}
    assert registration.starts["DICOM angles"] < min(v for k, v in registration.starts.items() if k != "DICOM angles")
    # Both views' Init imply one patient pose and Refine accepted nothing: one learned start, run once.
    assert len({round(v, 4) for k, v in registration.starts.items() if k != "DICOM angles"}) == 1
    # The learned start, far behind the DICOM angles' run after the coarse steps, stops there (tto.stop_behind); the
    # DICOM angles' run turned more than CONTINUE_TURN_DEG from its start and ran on (continuation.py).
    assert set(registration.tto_runs) == {"DICOM angles", "Init", CONTINUED_START}
    assert set(registration.tto_objective) == {"DICOM angles", CONTINUED_START}
    learned, dicom = registration.tto_runs["Init"], registration.tto_runs["DICOM angles"]
    assert learned.stopped_at == TTOSchedule(iterations=6).coarse_steps() + 1 and learned.behind > TTOSchedule().stop_behind
    assert dicom.stopped_at is None and dicom.behind is None and len(dicom.trace) == 7
    assert registration.chosen_start == min(registration.tto_objective, key=registration.tto_objective.get)
    assert result.tto is registration.tto_runs[registration.chosen_start]
    # The finalists and the continued run are compared by the objective of the opacified vessels it read.
    selection = registration.vessel_selection
    judge = result.renderer if selection is None else make_renderer(selection.volume, result.renderer.engine)
    final = sum(objective_value(judge, result.views[k].final_pose, result.views[k].prepared).loss for k in runs)
    assert final == pytest.approx(registration.tto_objective[registration.chosen_start], abs=1e-9)
    start = sum(objective_value(judge, registration.rig[k], result.views[k].prepared).loss for k in runs)
    assert final <= start + 1e-3
    lat = result.views["lat"].quality
    assert lat.flag != "ok" and any("reads this view as" in d for d in lat.reasons), lat
    assert not any("reads this view as" in d for d in result.views["pa"].quality.reasons)


def test_one_views_init_alone_is_a_start_when_the_other_view_is_far_off(phantom_case):
    """PA's Init 2 deg / 3 mm off, the lateral's 70 mm off in its own plane: the fused Init inherits
    the lateral's error, the PA Init alone does not; it wins the coarse steps of the TTO
    tournament and the result, which lands within 2 mm (carotid mPCD) of the truth in both views."""
    case = phantom_case
    N, true, cta, runs = _read_phantom(case)
    near_pa = _perturb(true["pa"], (1.0, -1.0, 1.0), (2.0, -1.0, 2.0))
    far_lat = _perturb(true["lat"], (2.0, 0.0, 0.0), (0.0, 50.0, -50.0))
    init = OracleInit([N @ isopose(C.VIEW_PA), N @ near_pa, N @ far_lat])
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    seen: list[float] = []
    result = register_case(
        cta, runs, models=oracle_models(init, OracleRefine([])), segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)),
        options=RegistrationOptions(backend="torch", device="cpu", tto=TTOSchedule(px=96, starts=5)),  # all five tried
        progress=lambda stage, f, message: seen.append(f) if stage == "tto" else None,
    )
    # The tournament's progress rises steadily through every start's share to the end.
    assert seen[-1] == 1.0 and all(b >= a for a, b in zip(seen, seen[1:]))
    assert max(b - a for a, b in zip(seen, seen[1:])) < 0.05
    registration = result.registration
    assert registration.starts["Init PA"] < min(registration.starts["Init"], registration.starts["Init LAT"])
    assert registration.chosen_start == "Init PA"
    # The record names every start's ranking loss and where the ones not kept stopped.
    record = build_record(result, runs)["registration"]
    ranking = record["tto_ranking_loss"]
    # The similarity search moved the fused Init (Refine accepted nothing): a start of its own.
    assert set(ranking) == set(registration.tto_runs) == {"DICOM angles", "Init", "Init PA", "Init LAT", "Refine + search"}
    assert ranking["Init PA"] == min(v for k, v in ranking.items() if k != "DICOM angles")
    # The DICOM angles' run, a finalist far behind Init PA's after the coarse steps, stops there too.
    assert record["tto_stopped_at"] == {"DICOM angles": 16, "Init": 16, "Init LAT": 16, "Refine + search": 16}
    assert set(record["tto_stopped_behind"]) == {"DICOM angles"} and record["tto_stopped_behind"]["DICOM angles"] > 0.2
    assert set(registration.tto_objective) == {"Init PA"}
    points = load_truth(case / "cta.nii.gz").carotid_points_mm
    for key in ("pa", "lat"):
        run = runs[key]
        error = evaluate_pose(result.views[key].final_pose, true[key], run.detector, run.angles.sod_mm, points)["mpcd_mm"]
        assert error < 2.0, (key, error)


def test_weak_image_evidence_keeps_the_networks_estimate(tmp_path, capsys):
    """The shipped 128-px phantom case with its arteries given: its runs hold little vessel evidence (vessel images
    NCC 0.10-0.22 with the true projection), and the TTO's tournament once ended 44 mm off from a networks' estimate
    of 0.97 / 0.79 mm (then: every objective near 0, above ``WEAK_OBJECTIVE``), from 2026-12-05 4.5 mm off with the
    CTA's vessels where the lateral run shows none (vessel NCC 0.06 < ``VESSEL_NCC_FAILED``), and since 2026-12-07
    (the vessel images' frames weighed by their noise) again at a weak best objective (-0.246). Either way the
    networks' estimate is kept (test_trust), and the record says why."""
    pytest.importorskip("torch")
    from geopose.register.cli import print_summary, register_files

    case = Path(__file__).resolve().parents[2] / "Resources" / "Testing" / "phantom_seed0_2mm"
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    segmentation = tmp_path / "vessels.nii.gz"
    from geopose.cta import save_volume
    save_volume(labels.like(L.vessel_mask(labels.array).astype(np.uint8)), segmentation)
    handed = []
    record = register_files(case / "cta.nii.gz", case / "dsa_pa.dcm", case / "dsa_lat.dcm", tmp_path / "out",
                            segmentation=segmentation, options=RegistrationOptions(device="cpu", backend="torch"),
                            estimate=handed.append)
    assert any("the networks' estimate (greedy Refine + search) was kept" in note for note in record["notes"])
    # the pairing test ran on the given segmentation, which can make the result doubtful but never fail it
    assert record["registration"]["pairing"]["given_segmentation"] and record["registration"]["pairing"]["verdict"] != "failed"
    # The networks' estimate was handed over once with the CTA and runs read (what the browser app shows meanwhile).
    assert len(handed) == 1 and set(handed[0].runs) == {"pa", "lat"} and handed[0].cta.shape_ijk == labels.shape_ijk
    for key in ("pa", "lat"):
        np.testing.assert_allclose(handed[0].preliminary.poses[key], record["views"][key]["stages"]["search"]["pose_centred"])
    for key in ("pa", "lat"):
        view = record["views"][key]
        assert view["truth"]["final"]["mpcd_mm"] == pytest.approx(view["truth"]["search"]["mpcd_mm"])
        assert view["truth"]["final"]["mpcd_mm"] < 2.0  # 0.97 / 0.79 measured
        assert view["quality"]["flag"] != "ok"
    # the console summary says why: each view's reasons under its line, then the notes not said there
    capsys.readouterr()
    print_summary(record, tmp_path / "out")
    printed = capsys.readouterr().out.splitlines()
    for key in ("pa", "lat"):
        line = next(i for i, text in enumerate(printed) if text.startswith(f"{key.upper():>3}: view"))
        reasons = record["views"][key]["quality"]["reasons"]
        assert reasons and printed[line + 1:line + 1 + len(reasons)] == [f"     - {r}" for r in reasons]
    said = {r for key in ("pa", "lat") for r in record["views"][key]["quality"]["reasons"]}
    assert [text for text in printed if text.startswith("note: ")] == [f"note: {n}" for n in record["notes"] if n not in said]
    assert all(printed.count(f"     - {n}") >= 1 for n in record["notes"] if n in said)


def test_the_published_pipeline_registers_each_view_on_its_own(phantom_case):
    """``independent_views=True`` (the paper's pipeline): each view's calibrated Init and greedy Refine, then the paper's
    TTO of each view's own pose. The networks' estimate (Refine's poses) is handed over once, after Refine and before
    the TTO, and the TTO brings each view nearer the truth than that estimate."""
    case = phantom_case
    N, true, cta, runs = _read_phantom(case)
    start = {k: _perturb(true[k]) for k in true}
    init = OracleInit([N @ isopose(C.VIEW_PA), N @ start["pa"], N @ start["lat"]])
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    stages = []
    result = register_case(
        cta, runs, models=oracle_models(init, OracleRefine([])), segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)),
        options=RegistrationOptions(backend="torch", device="cpu", independent_views=True, tto=TTOSchedule(iterations=12)),
        progress=lambda stage, f, msg: stages.append(stage), preliminary=stages.append,
    )
    assert result.registration.mode == "independent views" and result.registration.search is None
    handed = [s for s in stages if not isinstance(s, str)]
    assert len(handed) == 1 and handed[0].stage == "estimate"
    before = stages[:stages.index(handed[0])]
    assert "refine" in before and "tto" not in before and "tto" in stages[stages.index(handed[0]):]
    assert 0.0 < handed[0].elapsed_s < result.runtimes_s["total"]
    points = load_truth(case / "cta.nii.gz").carotid_points_mm
    for key in ("pa", "lat"):
        view = result.views[key]
        assert "search" not in view.stage_poses
        np.testing.assert_array_equal(handed[0].poses[key], view.refine.pose)
        # Identity residuals: Refine kept the view's own Init, which is its start (no combined patient pose here).
        np.testing.assert_allclose(view.refine.pose, start[key], atol=1e-6)
        run = runs[key]
        error = {stage: evaluate_pose(pose, true[key], run.detector, run.angles.sod_mm, points)["mpcd_mm"]
                 for stage, pose in (("estimate", view.refine.pose), ("final", view.final_pose))}
        assert error["final"] < 0.7 * error["estimate"], (key, error)
    assert len(result.tto.trace) == 13


def test_native_runs_register_as_their_subtracted_twins(tmp_path: Path, phantom_case: Path):
    """Runs archived native (radiographs with a Mask Subtraction Sequence, `geopose phantom --native-runs`) are read
    subtracted by their own headers: the networks' and the TTO's images match those of the same phantom's subtracted
    runs, and the user's path (`geopose register` with the CTA and the two native runs, masks computed) registers them
    and records how each was subtracted."""
    from geopose.dsa import read_dsa
    from geopose.dsa.preprocess import preprocess_dsa
    from geopose.phantom.cli import write_phantom
    from geopose.register.cli import register_files

    native = tmp_path / "native"
    write_phantom(12, native, spacing_mm=2.0, max_matrix_px=512, native_runs=True)  # phantom_case, archived native
    for key in ("pa", "lat"):
        a, b = (preprocess_dsa(read_dsa(folder / f"dsa_{key}.dcm")) for folder in (native, phantom_case))
        # 0.9993 / 0.9975 (PA) and 0.9993 / 0.9940 (LAT) measured: they differ by the subtracted runs' 8-bit rounding
        assert np.corrcoef(a.model_image.ravel(), b.model_image.ravel())[0, 1] > 0.99, key
        assert np.corrcoef(a.tto_vessels.ravel(), b.tto_vessels.ravel())[0, 1] > 0.98, key
    record = register_files(native / "cta.nii.gz", native / "dsa_pa.dcm", native / "dsa_lat.dcm", tmp_path / "out")
    assert not any("looks unsubtracted" in note for note in record["notes"])
    # a 2 mm CTA is too coarse for the artery classifier, so the pairing test did not run, and the record says so
    from geopose.register.pairing import NOT_RUN_NOTE
    assert record["registration"]["pairing"] is None and NOT_RUN_NOTE in record["notes"]
    # the same runs without their sequence are read as stored, radiographs: the registration says so
    import pydicom

    from geopose.dsa.subtraction import unsubtracted_notes, unsubtracted_ratio

    stripped = {}
    for key in ("pa", "lat"):
        ds = pydicom.dcmread(native / f"dsa_{key}.dcm")
        del ds.MaskSubtractionSequence
        ds.save_as(tmp_path / f"stripped_{key}.dcm")
        stripped[key] = read_dsa(tmp_path / f"stripped_{key}.dcm")
        assert unsubtracted_ratio(stripped[key].frames) > 30  # 72 / 49 measured; stored subtracted 0.60 / 0.52
    notes = unsubtracted_notes(stripped)
    assert len(notes) == 2 and notes[0].startswith("the PA run looks unsubtracted") and "export the run subtracted" in notes[0]
    assert unsubtracted_notes({key: read_dsa(phantom_case / f"dsa_{key}.dcm") for key in ("pa", "lat")}) == []
    for key in ("pa", "lat"):
        assert "AVG_SUB" in record["inputs"][f"dsa_{key}"]["subtraction"]
        assert record["views"][key]["truth"]["final"]["mpcd_mm"] < 2.0, key  # 0.93 / 0.71 mm (subtracted twin 0.87 / 1.11)
