"""Registration stages with ground-truth oracles in place of trained networks.

A phantom case (2 mm, written and read back through the real file formats) is
registered with an oracle Init that answers the true canonical poses, so the
calibration algebra, the greedy gate and the test-time optimisation are tested
against known answers without any trained weights.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import blob_renderer
from PIL import Image

from geopose import contract as C
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.geometry import invert, isopose, pose_from_params
from geopose.geometry.poses import axis_angle_to_matrix, matrix_to_axis_angle
from geopose.metrics import mncc
from geopose.metrics.measures import pose_error_components
from geopose.nets import ModelSet, load_models
from geopose.options import RegistrationOptions, SearchOptions
from geopose.phantom.cli import write_phantom, written_injected_arteries
from geopose.phantom import labels as L
from geopose.register import (
    PAPER_SCHEDULE,
    ConsoleProgress,
    Monitor,
    RegistrationCancelled,
    TTOSchedule,
    TTOView,
    calibrate,
    calibrated_init,
    greedy_refine,
    prepare_case,
    register_case,
    render_model_view,
    test_time_optimise as run_tto,
)
from geopose.register.biplane import common_axis, nominal_poses, turned_about
from geopose.register.evaluate import evaluate_pose, load_truth, truth_metrics
from geopose.register.objective import (PAPER_OBJECTIVE, SILHOUETTE_MODELS, SILHOUETTE_NOISE_EXPONENT,
                                        SILHOUETTE_NORM_PERCENTILE, Objective, clip_like_target, combine, fit_like_target,
                                        objective_value, silhouette_features, view_terms)
from geopose.register.tto import tto_views
from geopose.register.record import SCHEMA_VERSION, build_record
from geopose.register.report import write_overlays
from geopose.render.renderer import NumpyRenderer, TorchRenderer, make_renderer


#: mPCD (mm at the detector) the TTO must reach from a 5 deg / 10 mm perturbation when the
#: target is consistent with the objective (the DRR at the true pose): the issue's bar.
TTO_CONSISTENT_MPCD_MM = 1.0
#: ... and on the phantom's simulated DSA MAP (see test_oracle_registration_...).
TTO_ORACLE_MPCD_MM = 5.0
#: Network-input render size of the oracle "models".
ORACLE_RENDER_PX = 64


class OracleInit:
    """Answers queued canonical poses in call order (the view label from metadata)."""

    def __init__(self, answers: list[np.ndarray]):
        self.answers = list(answers)
        self.images: list[np.ndarray] = []

    def predict(self, image, is_lateral=None, mirror=True, view=None):
        self.images.append(image)
        pose = np.asarray(self.answers.pop(0), dtype=np.float64).reshape(1, 4, 4)
        if view is None:
            view = C.VIEW_LAT_PLUS if bool(np.asarray(is_lateral).reshape(-1)[0]) else C.VIEW_PA
        view = np.array([view]).reshape(1)
        return pose, view, np.eye(3)[view]


class OracleRefine:
    """Answers queued residuals ``D`` in order, one per image of a batch (identity once the queue is
    empty; the caller applies ``inverse(D) @ T``); ``answered`` counts them."""

    def __init__(self, residuals: list[np.ndarray]):
        self.residuals = list(residuals)
        self.answered = 0

    def predict_residual(self, target, render, view):
        self.answered += len(render)
        return np.stack([np.asarray(self.residuals.pop(0)).reshape(4, 4) if self.residuals else np.eye(4)
                         for _ in range(len(render))])


def oracle_models(init: OracleInit, refine: OracleRefine) -> ModelSet:
    return ModelSet(init, refine, render_px=ORACLE_RENDER_PX, runtime="torch")


def _perturb(T: np.ndarray, rot_deg=(3.0, -3.0, 2.0), trans_mm=(6.0, -5.0, 6.0)) -> np.ndarray:
    """A world-frame perturbation: rotation ~4.7 deg about the centre, translation ~9.8 mm."""
    D = pose_from_params(np.radians(rot_deg), np.zeros(3))
    D[:3, 3] = trans_mm
    return D @ np.asarray(T, dtype=np.float64)


@pytest.fixture(scope="module")
def phantom_case(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("case")
    # Seed 12: since the DICOM angles keep their signs (docs/conventions.md, section 7), seed 11's PA
    # (secondary +17.7 deg) has the GeoReg objective's own optimum 7 mm from the truth on its MAP
    # (mNCC 0.656 at the TTO result, 0.631 at the true pose): no case for the gain checked below.
    write_phantom(12, out, spacing_mm=2.0, max_matrix_px=512)
    return out


def _read_phantom(case: Path):
    """(native-to-canonical (4, 4), true camera-to-world poses per view, CTA, DSA runs) of a
    phantom folder written by ``geopose phantom``."""
    truth = json.loads((case / "truth.json").read_text())
    N = np.asarray(truth["native_to_canonical"], dtype=np.float64)
    true = {k: np.asarray(truth["views"][k]["pose_camera_to_world"]) for k in ("pa", "lat")}
    return N, true, load_cta(case / "cta.nii.gz"), {k: read_dsa(case / f"dsa_{k}.dcm") for k in ("pa", "lat")}


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
        progress=lambda stage, f, msg: stages.append(stage),
    )
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
    assert {"prepare", "calibration", "init", "refine", "search", "tto", "done"} <= set(stages)
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


def _prepared(case: Path):
    """(truth, runs, prepared case, torch renderer) of the phantom case, its vessels segmented."""
    truth = load_truth(case / "cta.nii.gz")
    cta = load_cta(case / "cta.nii.gz")
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    runs = {k: read_dsa(case / f"dsa_{k}.dcm") for k in ("pa", "lat")}
    prep = prepare_case(cta, runs, segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)), tto_px=128)
    return truth, runs, prep, TorchRenderer(prep.volume)


def test_tto_reaches_one_mm_on_a_consistent_target(phantom_case):
    """TTO from the true pose perturbed by ~4.7 deg / 9.8 mm, against targets rendered
    at the true pose (so the objective's optimum is the truth), reaches <= 1 mm mPCD."""
    truth, runs, prep, renderer = _prepared(phantom_case)
    views = []
    for key in ("pa", "lat"):
        p = prep.views[key]
        total, vessels = renderer.render(truth.poses[key], p.tto_detector, ("total", "vessels"))
        target = clip_like_target(total, p.tto_mask > 0, C.MAP_CLIP_PERCENTILES)
        views.append(TTOView(key, target, p.tto_mask, vessels, p.tto_detector, _perturb(truth.poses[key])))
    # The silhouette and vessel terms (the Dice term compares the CTA's cranium with the DSA's head mask).
    result = run_tto(renderer, views, TTOSchedule(), objective=Objective(ncc_weight=1.0),
                     rig=nominal_poses(runs))
    for view in views:
        run, true_pose = runs[view.name], truth.poses[view.name]
        before = evaluate_pose(view.pose, true_pose, run.detector, run.angles.sod_mm, truth.carotid_points_mm)
        after = evaluate_pose(result.poses[view.name], true_pose, run.detector, run.angles.sod_mm, truth.carotid_points_mm)
        assert before["mpcd_mm"] > 5.0, before
        assert after["mpcd_mm"] <= TTO_CONSISTENT_MPCD_MM, (view.name, before["mpcd_mm"], after["mpcd_mm"])
        assert after["rotation_error_deg"] < 0.5
    # The trace says which steps ran at half size (coarse to fine) and keeps the best full-size pose.
    sizes = [e["size"] for e in result.trace]
    assert sizes[: TTOSchedule().coarse_steps()] == ["half"] * TTOSchedule().coarse_steps() and sizes[-1] == "full"
    # The OneCycle peaks at the schedule's rates (rad, mm) and anneals to its final share of them, not to 0.
    rates = np.array([e["learning_rates"] for e in result.trace[:-1]])
    peak = np.array([TTOSchedule().rotation_lr_rad, TTOSchedule().translation_lr_mm])
    assert result.trace[-1]["learning_rates"] is None
    np.testing.assert_allclose(rates.max(axis=0), peak, rtol=0.05)
    np.testing.assert_allclose(rates[-1], TTOSchedule.final_lr_fraction * peak, rtol=1e-6)
    with pytest.raises(ValueError, match="share of the peak learning rate"):
        TTOSchedule(final_lr_fraction=0.0)


def test_common_axis_search_turns_the_patient_back(phantom_case):
    """On the simulated DSA pair, the patient turned 8 deg about the axis both image planes
    contain (out of plane in both views): the rotation prior holds most of that turn without the
    common-axis search (3 deg are left), and the search (two parabola steps of the default
    schedule) brings it back to <= 2 deg."""
    truth, runs, prep, renderer = _prepared(phantom_case)
    rig = nominal_poses(runs)
    X_true = truth.poses["pa"] @ invert(rig["pa"])
    X = turned_about(X_true, common_axis({k: X_true for k in rig}, rig), np.radians(8.0))
    views = tto_views(prep.views, {k: X @ A for k, A in rig.items()})

    def turn_deg(result) -> float:
        return float(np.degrees(np.linalg.norm(matrix_to_axis_angle(result.patient_pose[:3, :3] @ X_true[:3, :3].T))))

    held = run_tto(renderer, views, TTOSchedule(axis_search_at=()), rig=rig)
    searched = run_tto(renderer, views, TTOSchedule(), rig=rig)
    assert held.axis_searches == () and turn_deg(held) > 2.5, turn_deg(held)  # measured: 3.0 deg
    assert [s["iteration"] for s in searched.axis_searches] == [15, 18, 20, 22]
    # turned back, not further (measured -1.8 deg on the realistic phantom world, below -2 on the cleaner one)
    assert searched.axis_searches[0]["chosen_deg"] < -1.5, searched.axis_searches
    assert turn_deg(searched) <= 2.0, (turn_deg(searched), searched.axis_searches)  # measured: 1.5 deg


def test_the_shipped_refine_corrects_in_plane_shift_and_rotation(phantom_case):
    """One step of the shipped Refine, target the clean DRR at the truth, from the truth moved by
    6 deg about a random axis through the CTA centre and 10 mm: the in-plane shift and the rotation
    about the central ray both shrink (docs/training.md section 8: the Refine shipped before moved
    the shift but left the rotation, 2.67 -> 2.29 deg on validation phantoms)."""
    _, true, cta, runs = _read_phantom(phantom_case)
    models = load_models(runtime="torch")
    prep = prepare_case(cta, runs)
    renderer = NumpyRenderer(prep.volume)
    rng = np.random.default_rng(0)
    before, after = [], []
    for key in ("pa", "lat"):
        view = prep.views[key].view_label
        target = render_model_view(renderer, true[key], models.render_px)
        for _ in range(6):
            axis, shift = rng.normal(size=3), rng.normal(size=3)
            D = np.eye(4)
            D[:3, :3] = axis_angle_to_matrix(axis / np.linalg.norm(axis) * np.radians(6.0))
            D[:3, 3] = shift / np.linalg.norm(shift) * 10.0
            start = D @ true[key]
            image = render_model_view(renderer, start, models.render_px)
            moved = invert(models.refine.predict_residual(target, image, view)[0]) @ start
            before.append(pose_error_components(start, true[key]))
            after.append(pose_error_components(moved, true[key]))
    mean = lambda parts, name: float(np.mean([p[name] for p in parts]))  # noqa: E731
    assert mean(after, "in_plane_mm") < 0.6 * mean(before, "in_plane_mm")
    assert mean(after, "in_plane_rotation_deg") < 0.7 * mean(before, "in_plane_rotation_deg")


def test_calibration_with_perfect_network_recovers_native_pose():
    renderer = blob_renderer()
    g = np.random.default_rng(5)
    A = pose_from_params(g.normal(0, 0.2, 3), g.normal(0, 20, 3))
    t_cal = isopose(C.VIEW_PA)
    T_true = pose_from_params(np.array([1.5, 0.05, -0.1]), np.array([3.0, 700.0, -5.0]))
    A_inv = np.linalg.inv(A)
    oracle = OracleInit([A_inv @ t_cal, A_inv @ T_true])
    cal = calibrate(renderer, oracle, ORACLE_RENDER_PX)
    np.testing.assert_allclose(cal.frame_transfer, A, atol=1e-9)
    # The calibration image is the min-max DRR at the PA isopose in the model geometry.
    assert oracle.images[0].shape == (1, 1, C.MODEL_DETECTOR_PX, C.MODEL_DETECTOR_PX)
    np.testing.assert_allclose(oracle.images[0], render_model_view(renderer, t_cal, ORACLE_RENDER_PX))
    est = calibrated_init(np.random.rand(1, 1, 256, 256), True, oracle, cal)
    np.testing.assert_allclose(est.pose_native, T_true, atol=1e-9)
    assert est.view == C.VIEW_LAT_PLUS


def test_greedy_accepts_improvement_and_stops_at_first_rejection():
    renderer = blob_renderer()
    T_true = isopose(C.VIEW_PA)
    start = _perturb(T_true, (4.0, 0.0, 3.0), (8.0, 0.0, -6.0))
    target = render_model_view(renderer, T_true, ORACLE_RENDER_PX)
    # First residual brings the pose exactly to the truth (improves); the second moves it away (worse).
    D_good = start @ invert(T_true)  # inverse(D) @ start = T_true
    D_bad = invert(_perturb(T_true, (10.0, 5.0, 0.0), (30.0, 0.0, 0.0)) @ invert(T_true))
    oracle = OracleRefine([D_good, D_bad, np.eye(4)])
    trace = greedy_refine(renderer, target, start, C.VIEW_PA, oracle, ORACLE_RENDER_PX, max_proposals=5)
    assert [p.accepted for p in trace.proposals] == [True, False]
    assert oracle.answered == 2
    np.testing.assert_allclose(trace.pose, T_true, atol=1e-9)
    assert trace.mncc > trace.start_mncc
    assert trace.mncc == pytest.approx(mncc(target[0, 0], render_model_view(renderer, T_true, ORACLE_RENDER_PX)[0, 0]))


def test_cancel_hook_stops_a_stage():
    renderer = blob_renderer()
    T = isopose(C.VIEW_PA)
    target = render_model_view(renderer, T, ORACLE_RENDER_PX)
    with pytest.raises(RegistrationCancelled, match="refine"):
        greedy_refine(renderer, target, T, C.VIEW_PA, OracleRefine([]), ORACLE_RENDER_PX, monitor=Monitor(cancel=lambda: True))


def test_a_part_of_a_stage_reports_within_its_share():
    """Two TTO runs in one stage: the second's progress runs from 50 % to 100 %, labelled."""
    seen = []
    monitor = Monitor(lambda stage, f, m: seen.append((stage, f, m)))
    for i, name in enumerate(("Refine", "DICOM angles")):
        part = monitor.part(i, 2, f"from {name}")
        for f in (0.0, 0.5, 1.0, 1.5):
            part.step("tto", f, "iteration")
    assert [f for _, f, _ in seen] == [0.0, 0.25, 0.5, 0.5, 0.5, 0.75, 1.0, 1.0]
    assert seen[4] == ("tto", 0.5, "from DICOM angles: iteration")
    with pytest.raises(RegistrationCancelled, match="tto"):
        Monitor(cancel=lambda: True).part(1, 2, "x").step("tto", 0.1)


def test_console_bar_ends_its_line_when_a_stage_stops():
    """An error during a stage prints on a line of its own, not after the bar."""
    import io

    stream = io.StringIO()
    bar = ConsoleProgress(stream)
    bar("prepare", 0.5, "DSA LAT")
    bar.finish()
    assert stream.getvalue().endswith("DSA LAT".ljust(50) + "\n")
    bar.finish()  # nothing open: nothing written
    assert stream.getvalue().count("\n") == 1


def test_the_objective_is_the_same_in_numpy_and_in_the_tto(phantom_case):
    """The numpy score that picks the TTO's start and the torch loss the TTO minimises are one
    objective: every term agrees at the DICOM-angle pose and 5 deg / 10 mm away."""
    case = phantom_case
    cta = load_cta(case / "cta.nii.gz")
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    runs = {k: read_dsa(case / f"dsa_{k}.dcm") for k in ("pa", "lat")}
    prep = prepare_case(cta, runs, segmentation=labels.like(L.vessel_mask(labels.array).astype(np.uint8)), tto_px=96)
    rig = nominal_poses(runs)
    numpy_renderer, torch_renderer = NumpyRenderer(prep.volume), TorchRenderer(prep.volume)
    for X in (np.eye(4), _perturb(np.eye(4))):
        poses = {k: X @ rig[k] for k in rig}
        trace = run_tto(torch_renderer, tto_views(prep.views, poses), TTOSchedule(0), rig=rig).trace[0]
        total = 0.0
        for key in rig:
            value = objective_value(numpy_renderer, poses[key], prep.views[key])
            got = trace["views"][key]
            # 3e-3: the two kernels' sampling differs most at the DSA mask's edge (2.6e-3 on the silhouette
            # mNCC once the mask stopped following the vessels, dsa.preprocess.dsa_cranium_mask)
            assert value.vessel_ncc is not None and got["vessel_ncc"] == pytest.approx(value.vessel_ncc, abs=3e-3)
            assert got["mncc"] == pytest.approx(value.mncc, abs=3e-3)
            assert got["dice_loss"] == pytest.approx(value.dice_loss, abs=3e-3)
            total += value.loss
        assert trace["loss"] == pytest.approx(total, abs=4e-3)


def test_view_terms_agree_on_numpy_and_torch_arrays_for_every_silhouette_model():
    """The one objective (objective.view_terms) on the same images gives the same terms in numpy and torch:
    only the similarity kernels are written twice. The torch loss also carries a gradient."""
    import torch

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:48, :40]
    total = np.exp(-((yy - 24) ** 2 + (xx - 20) ** 2) / 200.0) * 5 + rng.normal(0, 0.05, (48, 40))
    cranium = total * 4 - 2
    vessels = np.maximum(0, np.sin(xx / 3.0)) * (total > 1)
    target = np.clip(total + rng.normal(0, 0.3, total.shape), 0.5, 4)
    mask = total > 0.8
    vessel_target = vessels + rng.normal(0, 0.1, vessels.shape)
    for model in SILHOUETTE_MODELS:
        objective = Objective(silhouette=model)
        ours = view_terms(total, cranium, vessels, target, mask, vessel_target, objective)
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        image = t(total).requires_grad_(True)
        theirs = view_terms(image, t(cranium), t(vessels), t(target), t(mask), t(vessel_target), objective,
                            vessel_term=True, xp=torch)
        for a, b in zip(ours, theirs):
            assert float(b.detach()) == pytest.approx(float(a), abs=2e-4), model
        theirs[0].sum().backward()
        assert float(image.grad.abs().sum()) > 0, model
    no_vessels = view_terms(total, cranium, np.zeros_like(vessels), target, mask, vessel_target, Objective())
    assert no_vessels[3] is None and no_vessels[0] == pytest.approx(combine(Objective(), *no_vessels[1:3], None))


def test_the_fitted_silhouette_is_the_least_squares_combination_of_its_basis():
    """A target made of the basis (u, exp(2 min(u, 1)), 1; u the DRR over its 99.5th percentile in
    the mask) with non-negative weights is recovered exactly, zero outside the mask, in numpy and in
    the TTO's torch; a target that inverts the DRR gets no inverted image (only its mean); an unknown
    silhouette model is refused when the objective is built."""
    import torch

    rng = np.random.default_rng(3)
    drr = rng.gamma(2.0, 1.5, (40, 52))
    mask = np.zeros(drr.shape)
    mask[4:36, 6:48] = 1
    u = drr / np.quantile(drr[mask > 0], SILHOUETTE_NORM_PERCENTILE / 100)
    target = (0.4 + 1.3 * u + 0.25 * np.exp(SILHOUETTE_NOISE_EXPONENT * np.minimum(u, 1.0))) * mask
    np.testing.assert_allclose(silhouette_features(drr, mask)[1], np.exp(2.0 * np.minimum(u, 1.0)))
    fitted = fit_like_target(drr, target + 5.0 * (1 - mask), mask)  # what lies outside the mask is not fitted
    np.testing.assert_allclose(fitted, target, atol=1e-9)
    as_t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    np.testing.assert_allclose(fit_like_target(as_t(drr), as_t(target), as_t(mask), xp=torch).numpy(), target, atol=1e-4)
    inverted = fit_like_target(drr, (3.0 - u) * mask, mask)
    np.testing.assert_allclose(inverted[mask > 0], np.mean(3.0 - u[mask > 0]))
    with pytest.raises(ValueError, match="silhouette must be one of"):
        Objective(silhouette="clip")


def test_the_fitted_silhouette_explains_the_map_better_than_the_clipped_drr(phantom_case):
    """At the true pose of a simulated run, the noise-level model fitted to the MAP's silhouette
    matches it better (mNCC) than the DRR clipped like it, in both views."""
    truth, runs, prep, _ = _prepared(phantom_case)
    renderer = NumpyRenderer(prep.volume)
    for key, view in prep.views.items():
        (total,) = renderer.render(truth.poses[key], view.tto_detector, ("total",))
        mask = view.tto_mask > 0
        clipped = mncc(view.tto_image, clip_like_target(total, mask, C.MAP_CLIP_PERCENTILES))
        fitted = mncc(view.tto_image, fit_like_target(total, view.tto_image, mask))
        assert fitted > clipped + 0.03, (key, clipped, fitted)


class SideSwappedInit(OracleInit):
    """An oracle Init whose view logits read the other lateral side than the one it is told."""

    def predict(self, image, is_lateral=None, mirror=True, view=None):
        pose, label, _ = super().predict(image, is_lateral, mirror, view)
        read = 2 - label if bool(np.asarray(is_lateral).reshape(-1)[0]) else label
        return pose, label, np.eye(3)[read]


def test_the_dicom_angles_result_is_kept_on_a_tie():
    """The lowest final objective wins; within OBJECTIVE_TIE of it, the DICOM angles' result does."""
    from geopose.register.starts import DICOM_START
    from geopose.register.tournament import OBJECTIVE_TIE, chosen_result

    assert chosen_result({DICOM_START: -0.46458, "Init PA": -0.46460}) == DICOM_START
    assert chosen_result({DICOM_START: -0.40, "Init": -0.40 - 2 * OBJECTIVE_TIE}) == "Init"
    assert chosen_result({"Init": -0.30, DICOM_START: -0.50}) == DICOM_START
    assert chosen_result({"Refine": -0.7}) == "Refine"


def test_a_bad_init_falls_back_to_the_dicom_angles_and_is_flagged(phantom_case):
    """Init 20 deg / 60 mm off, reading the lateral on the wrong side: the DICOM-angle pose scores
    best of the candidate starts, the TTO runs from it and from the one distinct learned start, the
    result comes from the DICOM angles' run and is no worse than that start by the same objective,
    and the lateral view carries the side doubt."""
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
    assert set(registration.tto_runs) == set(registration.tto_objective) == {"DICOM angles", "Init"}
    assert all(run.stopped_at is None and len(run.trace) == 7 for run in registration.tto_runs.values())
    assert registration.chosen_start == "DICOM angles" == min(registration.tto_objective, key=registration.tto_objective.get)
    assert result.tto is registration.tto_runs["DICOM angles"]
    # The finalists are compared by the objective of the opacified vessels read after the coarse steps.
    selection = registration.vessel_selection
    judge = result.renderer if selection is None else make_renderer(selection.volume, result.renderer.engine)
    final = sum(objective_value(judge, result.views[k].final_pose, result.views[k].prepared).loss for k in runs)
    assert final == pytest.approx(registration.tto_objective["DICOM angles"], abs=1e-9)
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
        options=RegistrationOptions(backend="torch", device="cpu", tto=TTOSchedule(px=96)),
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
    assert record["tto_stopped_at"] == {"Init": 16, "Init LAT": 16, "Refine + search": 16}
    assert set(registration.tto_objective) == {"DICOM angles", "Init PA"}
    points = load_truth(case / "cta.nii.gz").carotid_points_mm
    for key in ("pa", "lat"):
        run = runs[key]
        error = evaluate_pose(result.views[key].final_pose, true[key], run.detector, run.angles.sod_mm, points)["mpcd_mm"]
        assert error < 2.0, (key, error)


#: Drift (mPCD, mm at the detector) a TTO started at the truth may reach on the phantom's simulated
#: MAPs with the default objective: the issue's target is 0.5 mm mean over the benchmark; the bench
#: measures it (row "truth + 25 TTO (drift)"), this bounds one case per view.
TTO_DRIFT_BOUND_MM = 1.5


def test_tto_started_at_the_truth_stays_near_it(phantom_case):
    """The default objective's optimum on a simulated DSA pair lies near the truth: one patient pose,
    25 steps from the true pose, ends within TTO_DRIFT_BOUND_MM per view; the paper's objective, per
    view, drifts further on the same case."""
    truth, runs, prep, renderer = _prepared(phantom_case)

    def drift(poses: dict) -> dict[str, float]:
        return {k: evaluate_pose(poses[k], truth.poses[k], runs[k].detector, runs[k].angles.sod_mm,
                                 truth.carotid_points_mm)["mpcd_mm"] for k in runs}

    ours = drift(run_tto(renderer, tto_views(prep.views, truth.poses), rig=nominal_poses(runs)).poses)
    published = run_tto(renderer, tto_views(prep.views, truth.poses), PAPER_SCHEDULE, objective=PAPER_OBJECTIVE)
    paper = drift(published.poses)
    # The published schedule keeps PyTorch's OneCycle: it anneals to 1 / (25 x 1e4) of its peak.
    assert published.trace[-2]["learning_rates"] == [pytest.approx(PAPER_SCHEDULE.paper_lr * PAPER_SCHEDULE.final_lr_fraction)]
    assert max(ours.values()) <= TTO_DRIFT_BOUND_MM, ours
    assert sum(ours.values()) < sum(paper.values()), (ours, paper)


@pytest.fixture(scope="module")
def unilateral_case(tmp_path_factory) -> Path:
    """Phantom 12 with a selective left ICA injection: the CTA shows every artery, the runs a fifth of them."""
    out = tmp_path_factory.mktemp("unilateral")
    write_phantom(12, out, spacing_mm=2.0, max_matrix_px=512, injection="ica_left")
    return out


def test_the_opacified_vessels_read_near_the_truth_are_the_injected_ones(unilateral_case):
    """Read at the true pose, the kept vessel voxels are mostly the injected arteries (against a fifth
    of all vessels), most of those are kept; read 60 mm off, too few pass and all vessels stay."""
    from geopose.register.opacified import read_opacified, vessel_shift_mm

    truth, runs, prep, _ = _prepared(unilateral_case)
    rig = nominal_poses(runs)
    views = [(k, prep.views[k].tto_vessels, prep.views[k].tto_detector) for k in rig]
    vessels, injected = prep.volume.mask("vessels"), written_injected_arteries(unilateral_case)
    X = truth.poses["pa"] @ invert(rig["pa"])
    selection = read_opacified(prep.volume, X, rig, views)
    kept = selection.keep
    assert selection.applied and not (kept & ~vessels).any()
    base = injected[vessels].mean()
    precision, recall = injected[kept].mean(), kept[injected & vessels].mean()
    assert base < 0.3 and precision > 0.6 and recall > 0.5, (base, precision, recall)
    np.testing.assert_array_equal(selection.volume.mask("vessels"), kept)
    # How far a run's pose places the kept vessels from where they were read: a 10 mm shift is 10 mm.
    far = X.copy()
    far[:3, 3] += [6.0, 0.0, 8.0]
    assert vessel_shift_mm(prep.volume, selection, X) == pytest.approx(0.0, abs=1e-9)
    assert vessel_shift_mm(prep.volume, selection, far) == pytest.approx(10.0, abs=1e-6)
    far[:3, 3] += [54.0, 0.0, 52.0]
    missed = read_opacified(prep.volume, far, rig, views)
    assert not missed.applied and missed.keep.sum() == vessels.sum() and missed.volume is None
    assert read_opacified(prep.volume, X, rig, [(k, np.zeros_like(v), d) for k, v, d in views]) is None


def test_tto_from_the_truth_stays_with_the_opacified_vessels(unilateral_case):
    """The arteries a selective injection leaves empty pull the TTO off the truth when the vessel term
    compares all of the CTA's; after its coarse steps the TTO reads the opacified ones and keeps
    those, and then ends nearer the truth (experiments/tto_objective/objective.md)."""
    truth, runs, prep, renderer = _prepared(unilateral_case)
    rig = nominal_poses(runs)

    def drift(result) -> float:
        return max(evaluate_pose(result.poses[k], truth.poses[k], runs[k].detector, runs[k].angles.sod_mm,
                                 truth.carotid_points_mm)["mpcd_mm"] for k in runs)

    read = run_tto(renderer, tto_views(prep.views, truth.poses), rig=rig)
    every = run_tto(renderer, tto_views(prep.views, truth.poses), rig=rig, objective=Objective(read_opacified=False))
    selection = read.vessel_selection
    assert every.vessel_selection is None
    assert selection.applied and selection.iteration == TTOSchedule().coarse_steps() and selection.start == "start"
    assert 0.05 < selection.kept_fraction < 0.5
    assert drift(read) <= 0.5 and drift(read) < drift(every) - 0.3, (drift(read), drift(every))


def test_weak_image_evidence_keeps_the_networks_estimate(tmp_path):
    """The shipped 128-px phantom case with its arteries given: every start's objective stays near 0 (the
    runs hold little evidence), and the TTO's tournament once ended 44 mm off from a networks' estimate of
    0.97 / 0.79 mm. Above ``WEAK_OBJECTIVE`` the networks' estimate is kept, and the record says why."""
    pytest.importorskip("torch")
    from geopose.register.cli import register_files
    from geopose.register.trust import WEAK_OBJECTIVE

    case = Path(__file__).resolve().parents[2] / "Resources" / "Testing" / "phantom_seed0_2mm"
    labels = load_cta(case / "labels.nii.gz", check_hu=False)
    segmentation = tmp_path / "vessels.nii.gz"
    from geopose.cta import save_volume
    save_volume(labels.like(L.vessel_mask(labels.array).astype(np.uint8)), segmentation)
    record = register_files(case / "cta.nii.gz", case / "dsa_pa.dcm", case / "dsa_lat.dcm", tmp_path / "out",
                            segmentation=segmentation, options=RegistrationOptions(device="cpu", backend="torch"))
    assert min(record["registration"]["tto_objective"].values()) > WEAK_OBJECTIVE
    assert any("little image evidence" in note for note in record["notes"])
    for key in ("pa", "lat"):
        view = record["views"][key]
        assert view["truth"]["final"]["mpcd_mm"] == pytest.approx(view["truth"]["search"]["mpcd_mm"])
        assert view["truth"]["final"]["mpcd_mm"] < 2.0  # 0.97 / 0.79 measured
        assert view["quality"]["flag"] != "ok"
