"""One patient pose seen by both arms: the algebra ``T_v = X @ A_v``, the fusion of per-view
estimates by what each view observes, the views' disagreement along their common axis, the
biplane greedy refinement with an oracle network, and the pose error split by view axes."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import blob_renderer

from geopose import contract as C
from geopose.geometry import invert, pose_from_params
from geopose.geometry.detector import AP_REORIENT, CArmAngles, Detector
from geopose.geometry.poses import pose_from_carm_angles, project_points, rotation_angle_rad
from geopose.metrics import mncc
from geopose.metrics.measures import pose_error_components
from geopose.register import render_model_view
from geopose.register.biplane import (
    Observability,
    axis_disagreement_mm,
    common_axis,
    fuse_patient_poses,
    moved_by,
    part_way,
    patient_pose,
    turned_about,
    view_poses,
)
from geopose.options import RefineOptions, SearchOptions, TTOSchedule
from geopose.register.axis_search import valley_turn
from geopose.register.init import InitStage
from geopose.register.refine import refine_from_starts
from geopose.register.starts import refine_starts
from geopose.register.search import similarity_search

SID_MM, SOD_MM = 1200.0, 800.0
#: A PA + lateral rig as the DICOM angles give it (slightly oblique, like real runs).
RIG = {
    "pa": pose_from_carm_angles(CArmAngles(3.0, -4.0, SID_MM, SOD_MM)),
    "lat": pose_from_carm_angles(CArmAngles(88.0, 2.0, SID_MM, SOD_MM)),
}
RENDER_PX = 64


def _patient(rot_deg=(2.0, -3.0, 1.5), shift_mm=(4.0, -6.0, 3.0)) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = pose_from_params(np.radians(rot_deg), np.zeros(3))[:3, :3]
    X[:3, 3] = shift_mm
    return X


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix of ``deg`` about the unit ``axis`` (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _ray(key: str, X: np.ndarray = np.eye(4)) -> np.ndarray:
    """The view's central-ray direction in the CTA frame."""
    return (X @ RIG[key] @ AP_REORIENT)[:3, 2]


def test_one_patient_pose_places_both_cameras():
    X = _patient()
    cams = view_poses(X, RIG)
    for key in RIG:
        np.testing.assert_allclose(cams[key], X @ RIG[key], atol=1e-12)
        np.testing.assert_allclose(patient_pose(cams[key], RIG[key]), X, atol=1e-9)
    # The arms stay as the rig has them: the same relative pose whatever X is.
    np.testing.assert_allclose(invert(cams["pa"]) @ cams["lat"], invert(RIG["pa"]) @ RIG["lat"], atol=1e-9)
    # Identity is the DICOM-angle start.
    np.testing.assert_allclose(view_poses(np.eye(4), RIG)["lat"], RIG["lat"])


def test_fusion_takes_each_component_from_the_view_that_sees_it():
    X = _patient()
    assert fuse_patient_poses({"pa": X, "lat": X}, RIG) == pytest.approx(X, abs=1e-9)
    # PA misjudges its depth by 40 mm (along its own central ray), the lateral view is right: the lateral
    # view sees that direction in-plane, so the fused pose keeps only depth/(1 + depth) of the error.
    wrong = X.copy()
    wrong[:3, 3] += 40.0 * _ray("pa", X)
    fused = fuse_patient_poses({"pa": wrong, "lat": X}, RIG)
    error = fused[:3, 3] - X[:3, 3]
    obs = Observability()
    assert abs(np.dot(error, _ray("pa", X))) == pytest.approx(40.0 * obs.depth / (1 + obs.depth), rel=0.05)
    assert np.linalg.norm(error) < 1.0
    # An in-plane error seen by both views (the common superior-inferior axis) is averaged.
    common = np.cross(_ray("pa", X), _ray("lat", X))
    common /= np.linalg.norm(common)
    shifted = X.copy()
    shifted[:3, 3] += 10.0 * common
    fused = fuse_patient_poses({"pa": shifted, "lat": X}, RIG)
    assert np.dot(fused[:3, 3] - X[:3, 3], common) == pytest.approx(5.0, abs=0.3)
    # A rotation about PA's central ray is PA's in-plane rotation: the lateral view sees it out of
    # plane, so the fused rotation follows PA (weights 1 against out_of_plane).
    spun = X.copy()
    spun[:3, :3] = _rotation(_ray("pa", X), 6.0) @ X[:3, :3]
    fused = fuse_patient_poses({"pa": spun, "lat": X}, RIG)
    followed = np.degrees(rotation_angle_rad(fused[:3, :3] @ X[:3, :3].T))
    assert followed == pytest.approx(6.0 / (1 + obs.out_of_plane), rel=0.05)


def test_disagreement_is_measured_along_the_axis_both_views_see():
    X = _patient()
    common = np.cross(_ray("pa", X), _ray("lat", X))
    common /= np.linalg.norm(common)
    apart = X.copy()
    apart[:3, 3] += 25.0 * common + 30.0 * _ray("pa", X)  # the depth part does not count
    assert axis_disagreement_mm({"pa": apart, "lat": X}, RIG) == pytest.approx(25.0, abs=0.5)
    assert axis_disagreement_mm({"pa": X, "lat": X}, RIG) == pytest.approx(0.0, abs=1e-9)


def test_common_axis_is_normal_to_both_rays_and_only_it_is_held_by_the_tto_prior():
    """PA + lateral share the superior-inferior axis; the TTO's rotation prior costs a rotation
    about it and nothing for the rotations each view sees in-plane; one view has no common axis."""
    torch = pytest.importorskip("torch")
    from geopose.register.tto import _PatientParams

    X = _patient()
    axis = common_axis({"pa": X, "lat": X}, RIG)
    assert np.linalg.norm(axis) == pytest.approx(1.0)
    assert abs(axis @ _ray("pa", X)) < 1e-9 and abs(axis @ _ray("lat", X)) < 1e-9
    assert abs(axis @ (X[:3, :3] @ [0.0, 0.0, 1.0])) > 0.99  # the patient's superior axis (rig 2-4 deg oblique)
    assert common_axis({"pa": X}, RIG) is None
    turned = turned_about(X, axis, np.radians(5.0))  # about the axis through the isocentre: the axis stays
    assert np.allclose(turned[:3, 3], X[:3, 3]) and np.allclose(common_axis({"pa": turned, "lat": turned}, RIG), axis)
    assert np.degrees(np.arccos((np.trace(turned[:3, :3] @ X[:3, :3].T) - 1) / 2)) == pytest.approx(5.0)

    params = _PatientParams(X, RIG, "cpu")
    with torch.no_grad():
        params.w.copy_(torch.as_tensor(0.1 * axis))
        assert float(params.rotation_prior()) == pytest.approx(TTOSchedule.rotation_prior_per_rad2 * 0.01)
        for key in ("pa", "lat"):  # rotation about a central ray: in-plane in that view, free
            params.w.copy_(torch.as_tensor(0.1 * _ray(key, X)))
            assert float(params.rotation_prior()) == pytest.approx(0.0, abs=1e-12)
    alone = _PatientParams(X, {"pa": RIG["pa"]}, "cpu")
    with torch.no_grad():
        alone.w.copy_(torch.as_tensor(0.1 * _ray("pa", X)))
        assert float(alone.rotation_prior()) == pytest.approx(TTOSchedule.rotation_prior_per_rad2 * 0.01)


def test_the_valley_turn_moves_the_projections_least_and_the_tto_moves_along_it():
    """Along the common-axis valley (the turn with the other parameters' compensation) a head's
    points move less in both views than under the bare turn or any other compensation; the
    TTO's parameters follow it as ``moved_by`` does; one view or no points: no valley."""
    torch = pytest.importorskip("torch")
    from geopose.register.tto import _PatientParams

    g = np.random.default_rng(3)
    X = _patient()
    # vessels (mm, CTA frame): a cloud 40 mm from the isocentre, which a turn about it sweeps sideways
    # (measured: 0.47 px per degree along the valley, 0.61 for the bare turn)
    points = X[:3, 3] + [25.0, 20.0, 25.0] + g.normal(0.0, 1.0, (400, 3)) * [30.0, 20.0, 25.0]
    detectors = {key: Detector.model() for key in RIG}
    axis = common_axis({"pa": X, "lat": X}, RIG)

    def motion_px(rotation: np.ndarray, shift: np.ndarray, angle_rad: float = np.radians(1.0)) -> float:
        Y = moved_by(X, angle_rad * rotation, angle_rad * shift)
        return float(np.sqrt(np.mean([np.sum((project_points(Y @ RIG[k], detectors[k], points)[0]
                                              - project_points(X @ RIG[k], detectors[k], points)[0]) ** 2, axis=1)
                                      for k in RIG])))

    rotation, shift = valley_turn(X, RIG, detectors, points)
    assert rotation @ axis == pytest.approx(1.0)
    along = motion_px(rotation, shift)
    assert along < 0.85 * motion_px(axis, np.zeros(3)), (along, motion_px(axis, np.zeros(3)))
    normal = np.linalg.svd(axis[None])[2][1:]
    for _ in range(5):  # any other compensation moves the points more
        other = rotation + normal.T @ g.normal(0.0, 0.05, 2)
        assert motion_px(other, shift + g.normal(0.0, 3.0, 3)) > along
    assert valley_turn(X, {"pa": RIG["pa"]}, detectors, points) is None
    assert valley_turn(X, RIG, detectors, np.zeros((0, 3))) is None

    params = _PatientParams(X, RIG, "cpu")
    with torch.no_grad():
        params.move_along((params.w.detach().clone(), params.v.detach().clone()), (rotation, shift), 0.1)
        assert np.allclose(params.patient().numpy(), moved_by(X, 0.1 * rotation, 0.1 * shift), atol=1e-9)


class QueuedRefine:
    """A Refine network answering queued residuals ``D`` in order, one per image of each batch (the
    caller applies ``inverse(D) @ T``); ``answered`` counts them and ``batches`` the batch sizes."""

    def __init__(self, residuals: list[np.ndarray]):
        self.residuals, self.answered, self.batches = list(residuals), 0, []

    def predict_residual(self, target, render, view):
        assert len(target) == len(render)
        self.answered += len(render)
        self.batches.append(len(render))
        return np.stack([np.asarray(self.residuals.pop(0)) for _ in range(len(render))])


def test_biplane_greedy_fuses_both_views_retries_half_a_rejected_move_and_stops():
    renderer = blob_renderer()
    X_true = _patient()
    truth = view_poses(X_true, RIG)
    targets = {k: render_model_view(renderer, truth[k], RENDER_PX) for k in RIG}
    start = _patient((5.0, -1.0, 4.0), (-8.0, 10.0, 6.0))
    overshoot = part_way(start, X_true, 3.0)  # twice the start's error, on the other side
    halfway = part_way(start, X_true, 1.5)  # its half: half the start's error
    away = _patient((8.0, 0.0, 5.0), (25.0, 0.0, 0.0))

    def towards(X, Y):  # each view's residual from patient pose X to Y
        return [(X @ RIG[k]) @ invert(Y @ RIG[k]) for k in RIG]

    # Proposal 1 overshoots (rejected), its half-size retry is accepted; proposal 2 answers the truth
    # (accepted); proposal 3 heads far away: it and its retry are rejected and the loop stops.
    oracle = QueuedRefine(towards(start, overshoot) + towards(halfway, X_true) + towards(X_true, away))
    traces = refine_from_starts(renderer, targets, {"start": start}, RIG, {"pa": C.VIEW_PA, "lat": C.VIEW_LAT_PLUS}, oracle,
                                RENDER_PX, options=RefineOptions(steps=5)).traces
    for key in RIG:
        assert [p.accepted for p in traces[key].proposals] == [False, True, True, False, False]
        np.testing.assert_allclose(traces[key].proposals[1].pose, halfway @ RIG[key], atol=1e-6)
        np.testing.assert_allclose(traces[key].proposals[4].pose, part_way(X_true, away, 0.5) @ RIG[key], atol=1e-6)
        np.testing.assert_allclose(traces[key].pose, truth[key], atol=1e-6)
        best = mncc(targets[key][0, 0], targets[key][0, 0])  # the target against itself
        assert traces[key].mncc == pytest.approx(best, abs=1e-6) and traces[key].start_mncc < best - 0.05
    # Every proposal is one patient pose: the views' proposed poses keep the rig's relative pose.
    rel = invert(traces["pa"].proposals[3].pose) @ traces["lat"].proposals[3].pose
    np.testing.assert_allclose(rel, invert(RIG["pa"]) @ RIG["lat"], atol=1e-6)
    assert oracle.answered == 6


def test_refine_starts_pair_every_rotation_with_every_isocentre():
    pa, lat = _patient((6.0, -2.0, 1.0), (12.0, -3.0, 40.0)), _patient((-1.0, 4.0, -2.0), (-5.0, 30.0, 2.0))
    fused = fuse_patient_poses({"pa": pa, "lat": lat}, RIG)
    starts = refine_starts(InitStage({}, {"pa": pa, "lat": lat}, fused, 0.0))
    assert len(starts) == 9
    np.testing.assert_allclose(next(iter(starts.values())), fused, atol=1e-12)  # the fused pose comes first
    sources = {"fused": fused, "PA": pa, "LAT": lat}
    for r in sources:
        for t in sources:
            X = starts[f"rotation {r}, isocentre {t}"]
            np.testing.assert_allclose(X[:3, :3], sources[r][:3, :3], atol=1e-12)
            np.testing.assert_allclose(X[:3, 3], sources[t][:3, 3], atol=1e-12)
            np.testing.assert_allclose(X[3], [0, 0, 0, 1])


def test_refine_from_starts_keeps_the_most_similar_end():
    renderer = blob_renderer()
    X_true = _patient()
    truth = view_poses(X_true, RIG)
    targets = {k: render_model_view(renderer, truth[k], RENDER_PX) for k in RIG}
    far, near = _patient((9.0, 4.0, -6.0), (-15.0, 12.0, 20.0)), _patient((4.0, -1.0, 3.0), (8.0, -2.0, 6.0))
    stay = [np.eye(4)] * 2  # a residual of nothing for each view: the move is rejected and the loop stops
    towards = [(near @ RIG[k]) @ invert(X_true @ RIG[k]) for k in RIG]
    # The far start stays put; from the near one Refine answers the truth, then nothing. The starts run
    # in lockstep, one batch per view: (far, near) for PA, then for LAT, then the near start alone.
    oracle = QueuedRefine([stay[0], towards[0], stay[1], towards[1]] + stay)
    views = {"pa": C.VIEW_PA, "lat": C.VIEW_LAT_PLUS}
    result = refine_from_starts(renderer, targets, {"far": far, "near": near}, RIG, views, oracle, RENDER_PX)
    assert result.start == "near" and oracle.batches == [2, 2, 1, 1]
    for key in RIG:
        np.testing.assert_allclose(result.traces[key].pose, truth[key], atol=1e-6)
        np.testing.assert_allclose(result.traces[key].start_pose, near @ RIG[key], atol=1e-12)
    far_score = np.mean([mncc(targets[k][0, 0], render_model_view(renderer, far @ RIG[k], RENDER_PX)[0, 0]) for k in RIG])
    assert result.mncc["far"] == pytest.approx(far_score, abs=1e-9)
    assert result.mncc["near"] == pytest.approx(np.mean([mncc(t[0, 0], t[0, 0]) for t in targets.values()]), abs=1e-6)
    assert result.mncc["near"] > result.mncc["far"] + 0.05


def test_part_way_scales_the_turn_and_the_shift():
    X, Y = _patient(), _patient((6.0, 1.0, -3.0), (10.0, -4.0, 2.0))
    np.testing.assert_allclose(part_way(X, Y, 0.0), X, atol=1e-12)
    np.testing.assert_allclose(part_way(X, Y, 1.0), Y, atol=1e-12)
    half = part_way(X, Y, 0.5)
    np.testing.assert_allclose(part_way(X, half, 2.0), Y, atol=1e-12)  # two halves make the whole
    assert rotation_angle_rad(half[:3, :3] @ X[:3, :3].T) == pytest.approx(
        0.5 * rotation_angle_rad(Y[:3, :3] @ X[:3, :3].T), rel=1e-9)
    np.testing.assert_allclose(half[:3, 3], (X[:3, 3] + Y[:3, 3]) / 2, atol=1e-12)


def test_pose_error_components_split_by_the_true_camera_axes():
    true = RIG["pa"]
    cam = true @ AP_REORIENT
    # Move the camera 5 mm along its central ray (depth) and 3 mm along its image x axis.
    moved = true.copy()
    moved[:3, 3] += 5.0 * cam[:3, 2] + 3.0 * cam[:3, 0]
    parts = pose_error_components(moved, true)
    assert parts["depth_mm"] == pytest.approx(5.0, abs=1e-9) and parts["in_plane_mm"] == pytest.approx(3.0, abs=1e-9)
    assert parts["in_plane_rotation_deg"] == pytest.approx(0.0, abs=1e-9)
    # Spin the camera 4 deg about its central ray through the source: in-plane rotation only (and the
    # CTA centre swings in the image plane, not in depth).
    spun = true.copy()
    spun[:3, :3] = _rotation(cam[:3, 2], 4.0) @ true[:3, :3]
    parts = pose_error_components(spun, true)
    assert parts["in_plane_rotation_deg"] == pytest.approx(4.0, abs=1e-6)
    assert parts["out_of_plane_rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    assert parts["depth_mm"] == pytest.approx(0.0, abs=1e-6)
    # Tilt it 3 deg about its image x axis through the source: out-of-plane rotation only.
    tilted = true.copy()
    tilted[:3, :3] = _rotation(cam[:3, 0], 3.0) @ true[:3, :3]
    parts = pose_error_components(tilted, true)
    assert parts["out_of_plane_rotation_deg"] == pytest.approx(3.0, abs=1e-6)
    assert parts["in_plane_rotation_deg"] == pytest.approx(0.0, abs=1e-6)


def test_stage_agreement_measures_the_patient_not_the_source():
    """A 6.4 deg turn of the patient about the CTA centre moves the PA source by about 73 mm but
    the CTA centre in the camera frame by nothing: the quality rule's agreement sees 6.4 deg / 0 mm;
    a shift of the patient reads as its length."""
    from geopose.register.trust import stage_agreement

    learned = RIG["pa"]
    turn = np.eye(4)
    turn[:3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), 6.4)
    deg, mm = stage_agreement(learned, turn @ learned)
    assert deg == pytest.approx(6.4, abs=1e-6) and mm == pytest.approx(0.0, abs=1e-9)
    assert np.linalg.norm((turn @ learned)[:3, 3] - learned[:3, 3]) > 70.0
    shift = np.eye(4)
    shift[:3, 3] = [3.0, -4.0, 11.0]
    deg, mm = stage_agreement(learned, shift @ learned)
    assert deg == pytest.approx(0.0, abs=1e-4) and mm == pytest.approx(np.linalg.norm(shift[:3, 3]), abs=1e-9)


def test_similarity_search_recovers_shift_and_in_plane_turns_and_keeps_the_truth():
    renderer = blob_renderer()
    X_true = _patient()
    truth = view_poses(X_true, RIG)
    targets = {k: render_model_view(renderer, truth[k], RENDER_PX) for k in RIG}
    # Started at the truth: every neighbour scores lower, nothing moves; 10 moves per step size.
    kept = similarity_search(renderer, targets, X_true, RIG, RENDER_PX)
    assert kept.moves == () and kept.evaluations == 1 + 11 * len(SearchOptions.schedule)
    np.testing.assert_allclose(kept.patient_pose, X_true, atol=1e-12)
    # Off by a shift in every axis and a turn about each central ray (each view's in-plane rotation).
    start = moved_by(X_true, np.radians(3.0) * _ray("pa", X_true) - np.radians(2.0) * _ray("lat", X_true),
                     np.array([5.0, -3.0, 2.0]))
    found = similarity_search(renderer, targets, start, RIG, RENDER_PX)
    assert found.mncc > found.start_mncc + 0.05
    # Within the finest step of the truth (1 mm, 1 deg), from 6.2 mm and 3.6 deg.
    assert np.linalg.norm(found.patient_pose[:3, 3] - X_true[:3, 3]) <= 1.0
    assert np.degrees(rotation_angle_rad(found.patient_pose[:3, :3] @ X_true[:3, :3].T)) <= 1.0
    assert {name for name, _ in found.moves} <= {"shift x (mm)", "shift y (mm)", "shift z (mm)",
                                                  "turn about the PA ray (deg)", "turn about the LAT ray (deg)"}
    assert {abs(step) for _, step in found.moves} <= {step for step, _ in SearchOptions.schedule}
