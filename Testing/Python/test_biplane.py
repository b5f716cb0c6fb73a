"""One patient pose seen by both arms (``biplane.py``): the algebra ``T_v = X @ A_v``, the fusion of
per-view estimates by what each view observes, the views' disagreement along their common axis,
that axis (and the TTO's rotation prior about it), a part of the way between two patient poses, and
the pose error split by view axes."""

from __future__ import annotations

import numpy as np
import pytest
from register_helpers import RIG, _patient, _ray, _rotation

from geopose.geometry import invert
from geopose.geometry.poses import rotation_angle_rad
from geopose.options import TTOSchedule
from geopose.register.biplane import (
    Observability,
    axis_disagreement_mm,
    common_axis,
    fuse_patient_poses,
    part_way,
    patient_pose,
    turned_about,
    view_poses,
)


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


def test_part_way_scales_the_turn_and_the_shift():
    X, Y = _patient(), _patient((6.0, 1.0, -3.0), (10.0, -4.0, 2.0))
    np.testing.assert_allclose(part_way(X, Y, 0.0), X, atol=1e-12)
    np.testing.assert_allclose(part_way(X, Y, 1.0), Y, atol=1e-12)
    half = part_way(X, Y, 0.5)
    np.testing.assert_allclose(part_way(X, half, 2.0), Y, atol=1e-12)  # two halves make the whole
    assert rotation_angle_rad(half[:3, :3] @ X[:3, :3].T) == pytest.approx(
        0.5 * rotation_angle_rad(Y[:3, :3] @ X[:3, :3].T), rel=1e-9)
    np.testing.assert_allclose(half[:3, 3], (X[:3, 3] + Y[:3, 3]) / 2, atol=1e-12)

