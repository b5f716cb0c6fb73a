"""Rigid algebra (numpy, and the torch twin it must equal), the isopose table of
docs/conventions.md, DICOM angles, projection, frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from geopose import contract as C
from geopose.geometry import (
    AP_REORIENT,
    CArmAngles,
    Detector,
    RigidTransform,
    carm_angles_from_pose,
    invert,
    isopose,
    pose_from_carm_angles,
    pose_to_patient,
    pose_from_patient,
    project_points,
    project_points_tensor,
    ray_points_tensor,
    source_and_detector_points,
    view_from_primary_angle,
)
from geopose.geometry import poses as N
from geopose.geometry.rigid import (
    axis_angle_to_matrix,
    euler_zyx_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler_zyx,
    params_from_pose,
    pose_from_params,
)
from geopose.volume import Volume


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_euler_round_trip_and_order(dtype):
    g = torch.Generator().manual_seed(0)
    r = (torch.rand(64, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([6.0, 3.0, 6.0], dtype=dtype)
    R = euler_zyx_to_matrix(r)
    assert R.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    assert torch.allclose(matrix_to_euler_zyx(R), r, atol=tol * 10)
    # ZYX: first angle about z applied last, i.e. R = Rz @ Ry @ Rx.
    rz = euler_zyx_to_matrix(torch.tensor([[0.3, 0.0, 0.0]], dtype=dtype))
    ry = euler_zyx_to_matrix(torch.tensor([[0.0, 0.2, 0.0]], dtype=dtype))
    rx = euler_zyx_to_matrix(torch.tensor([[0.0, 0.0, -0.4]], dtype=dtype))
    both = euler_zyx_to_matrix(torch.tensor([[0.3, 0.2, -0.4]], dtype=dtype))
    assert torch.allclose(both, rz @ ry @ rx, atol=tol)
    # A rotation about z by +90 deg takes +x to +y.
    q = euler_zyx_to_matrix(torch.tensor([[math.pi / 2, 0, 0]], dtype=dtype))[0]
    assert torch.allclose(q @ torch.tensor([1.0, 0, 0], dtype=dtype), torch.tensor([0.0, 1, 0], dtype=dtype), atol=tol)


def test_axis_angle_round_trip_small_and_near_pi():
    g = torch.Generator().manual_seed(1)
    axes = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    angles = torch.cat([torch.tensor([0.0, 1e-7, 1e-3]), torch.linspace(0.1, 3.0, 44), torch.tensor([math.pi - 1e-5] * 3)])
    w = axes * angles[:, None].double()
    w2 = matrix_to_axis_angle(axis_angle_to_matrix(w))
    assert torch.allclose(axis_angle_to_matrix(w2), axis_angle_to_matrix(w), atol=1e-8)
    assert torch.allclose(w2[:-3], w[:-3], atol=1e-8)
    # Gradient at zero is finite (used by the Refine residuals and TTO).
    z = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(z).sum().backward()
    assert torch.isfinite(z.grad).all()


def test_pose_params_rule_translation_in_rotated_frame():
    r = torch.tensor([[0.4, -0.2, 0.1]], dtype=torch.float64)
    t = torch.tensor([[5.0, 650.0, -3.0]], dtype=torch.float64)
    T = pose_from_params(r, t)
    R = euler_zyx_to_matrix(r)[0]
    assert torch.allclose(T[0, :3, 3], R @ t[0])
    r2, t2 = params_from_pose(T)
    assert torch.allclose(r2, r) and torch.allclose(t2, t)


def test_rigid_compose_inverse_apply():
    g = torch.Generator().manual_seed(2)
    A = RigidTransform.from_euler_zyx(torch.randn(4, 3, generator=g), torch.randn(4, 3, generator=g) * 50)
    B = RigidTransform.from_axis_angle(torch.randn(4, 3, generator=g) * 0.3, torch.randn(4, 3, generator=g) * 10)
    I = (A @ A.inverse()).matrix
    assert torch.allclose(I, torch.eye(4).expand(4, 4, 4), atol=1e-5)
    p = torch.randn(4, 7, 3, generator=g) * 100
    assert torch.allclose((A @ B).apply(p), A.apply(B.apply(p)), atol=1e-3)
    assert torch.allclose(A.inverse().apply(A.apply(p)), p, atol=1e-3)
    with pytest.raises(ValueError, match="4, 4"):
        RigidTransform(torch.eye(3))


# The isopose table of docs/conventions.md section 2: source, detector centre, row-0 and column-0 directions.
ISOPOSE_TABLE = {
    C.VIEW_PA: ((0, 650, 0), (0, -370, 0), (0, 0, 1), (1, 0, 0)),
    C.VIEW_LAT_PLUS: ((-650, 0, 0), (370, 0, 0), (0, 0, 1), (0, 1, 0)),
    C.VIEW_LAT_MINUS: ((650, 0, 0), (-370, 0, 0), (0, 0, 1), (0, -1, 0)),
}


@pytest.mark.parametrize("view", [C.VIEW_LAT_MINUS, C.VIEW_PA, C.VIEW_LAT_PLUS])
def test_isopose_table(view):
    src_ref, det_ref, row0_dir, col0_dir = (np.asarray(v, dtype=np.float64) for v in ISOPOSE_TABLE[view])
    det = Detector.model()
    src, pix = source_and_detector_points(isopose(view), det)
    np.testing.assert_allclose(src, src_ref, atol=1e-9)
    H, W = det.shape
    centre = pix[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].reshape(-1, 3).mean(0)
    np.testing.assert_allclose(centre, det_ref, atol=1e-9)
    # Row 0 lies towards +z; column 0 towards the tabulated direction.
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    np.testing.assert_allclose(unit(pix[0, W // 2] - pix[-1, W // 2]), row0_dir, atol=1e-9)
    np.testing.assert_allclose(unit(pix[H // 2, 0] - pix[H // 2, -1]), col0_dir, atol=1e-9)
    # Detector plane SDD from the source, spacing 1.2 mm.
    assert np.linalg.norm(centre - src) == pytest.approx(C.MODEL_SDD_MM)
    assert np.linalg.norm(pix[0, 0] - pix[0, 1]) == pytest.approx(C.MODEL_PIXEL_SPACING_MM)
    # The torch rays of the DRR kernel are the same points.
    src_t, pix_t = ray_points_tensor(torch.as_tensor(isopose(view))[None], det)
    np.testing.assert_allclose(pix_t[0].numpy(), pix, atol=1e-9)
    np.testing.assert_allclose(src_t[0].numpy(), src, atol=1e-9)


@pytest.mark.parametrize(
    "alpha,view", [(0, C.VIEW_PA), (30, C.VIEW_PA), (-44, C.VIEW_PA), (-90, C.VIEW_LAT_MINUS), (-46, C.VIEW_LAT_MINUS),
                   (90, C.VIEW_LAT_PLUS), (84, C.VIEW_LAT_PLUS), (-115, C.VIEW_LAT_MINUS)]
)
def test_view_rule(alpha, view):
    """RAO (negative primary) is LAT-, LAO is LAT+ (docs/conventions.md, section 7)."""
    assert view_from_primary_angle(alpha) == view


def test_carm_angles_two_way():
    det_sdd = 1086.0
    for a in (0.0, -90.0, 90.0, -32.0, 15.0):
        ang = CArmAngles(primary_deg=a, secondary_deg=2.0, sid_mm=det_sdd, sod_mm=720.0)
        T = pose_from_carm_angles(ang)
        back = carm_angles_from_pose(T, sid_mm=det_sdd)
        assert back.primary_deg == pytest.approx(a, abs=1e-9)
        assert back.secondary_deg == pytest.approx(2.0, abs=1e-9)
        assert back.sod_mm == pytest.approx(720.0)
        src, _ = source_and_detector_points(T, Detector(8, 8, (1.0, 1.0), det_sdd))
        assert np.linalg.norm(src) == pytest.approx(720.0)
    # Primary 0 / SOD 650 is the PA isopose; -90 (RAO) is LAT-, +90 (LAO) LAT+.
    for a, view in ((0.0, C.VIEW_PA), (-90.0, C.VIEW_LAT_MINUS), (90.0, C.VIEW_LAT_PLUS)):
        T = pose_from_carm_angles(CArmAngles(a, 0.0, C.MODEL_SDD_MM, C.SOURCE_TO_ISOCENTER_MM))
        np.testing.assert_allclose(T, isopose(view), atol=1e-9)
    # Cranial tilt (positive secondary) tilts the real detector towards the head; the model
    # source takes the detector's side, so it moves towards +z (superior).
    T = pose_from_carm_angles(CArmAngles(0.0, 20.0, 1020.0, 650.0))
    src, pix = source_and_detector_points(T, Detector(2, 2, (1.0, 1.0), 1020.0))
    assert src[2] > 100 and pix.reshape(-1, 3)[:, 2].mean() < -100


def test_projection_by_hand_and_through_the_pixel():
    det = Detector(rows=100, cols=120, spacing_mm=(0.5, 0.4), sdd_mm=1000.0)
    T = isopose(C.VIEW_PA)
    # PA: source at y = +650, detector plane at y = -350; magnification 1000/650 at the isocentre.
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 13.0], [5.0, 325.0, -4.0]])
    rc, depth = project_points(T, det, pts)
    cr, cc = (100 - 1) / 2, (120 - 1) / 2
    m = 1000.0 / 650.0
    np.testing.assert_allclose(rc[0], [cr, cc])
    np.testing.assert_allclose(rc[1], [cr, cc - 10 * m / 0.4])  # +x -> towards column 0
    np.testing.assert_allclose(rc[2], [cr - 13 * m / 0.5, cc])  # +z -> towards row 0
    m2 = 1000.0 / 325.0
    np.testing.assert_allclose(rc[3], [cr + 4 * m2 / 0.5, cc - 5 * m2 / 0.4])
    np.testing.assert_allclose(depth[:3], 650.0)
    # Each point lies on the ray from the source through its pixel's point on the detector.
    M = T @ AP_REORIENT
    pix_world = det.pixel_to_camera(rc) @ M[:3, :3].T + M[:3, 3]
    v, d = pts - M[:3, 3], pix_world - M[:3, 3]
    assert np.linalg.norm(np.cross(v, d / np.linalg.norm(d, axis=1, keepdims=True)), axis=1).max() < 1e-9
    # Batched poses give the same as one pose at a time, and the torch projection agrees.
    both, _ = project_points(np.stack((T, isopose(C.VIEW_LAT_PLUS))), det, pts)
    np.testing.assert_allclose(both[0], rc)
    np.testing.assert_allclose(both[1], project_points(isopose(C.VIEW_LAT_PLUS), det, pts)[0])
    rc_t, _ = project_points_tensor(torch.as_tensor(T)[None], det, torch.as_tensor(pts))
    np.testing.assert_allclose(rc_t[0].numpy(), rc, atol=1e-9)
    # Principal offset shifts the image.
    det2 = Detector(100, 120, (0.5, 0.4), 1000.0, principal_offset_mm=(4.0, 0.0))
    rc2, _ = project_points(T, det2, pts[:1])
    assert rc2[0, 1] == pytest.approx(cc + 10.0)


def test_numpy_pose_algebra_equals_the_torch_twin():
    g = np.random.default_rng(4)
    r, t = g.uniform(-2, 2, (16, 3)), g.normal(0, 100, (16, 3))
    for rotation in ("euler_zyx", "axis_angle"):
        ours = N.pose_from_params(r, t, rotation=rotation)
        theirs = pose_from_params(torch.as_tensor(r), torch.as_tensor(t), rotation=rotation).numpy()
        np.testing.assert_allclose(ours, theirs, atol=1e-12)
    T = N.pose_from_params(r, t)
    r2, t2 = N.params_from_pose(T)
    rt, tt = params_from_pose(torch.as_tensor(T))
    np.testing.assert_allclose(r2, rt.numpy(), atol=1e-12)
    np.testing.assert_allclose(t2, tt.numpy(), atol=1e-9)
    np.testing.assert_allclose(invert(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-9)
    np.testing.assert_allclose(N.matrix_to_euler_zyx(N.euler_zyx_to_matrix(r[:, :] * [1, 0.7, 1])), r * [1, 0.7, 1], atol=1e-9)
    np.testing.assert_allclose(N.rotation_angle_rad(N.axis_angle_to_matrix(np.array([[0.0, 0.3, 0.4]]))), [0.5])


def test_intrinsic_matrix_agrees_with_projection():
    det = Detector(64, 80, (0.7, 0.5), 1100.0, principal_offset_mm=(1.5, -2.0))
    cam = torch.tensor([[12.0, -7.0, 700.0], [-30.0, 25.0, 900.0]], dtype=torch.float64)
    h = cam @ torch.as_tensor(det.intrinsic_matrix()).T
    colrow = h[:, :2] / h[:, 2:]
    rc = det.camera_to_pixel(cam)
    assert torch.allclose(colrow.flip(-1), rc)


def test_detector_rejects_bad_values():
    with pytest.raises(ValueError, match="spacing"):
        Detector(10, 10, (0.0, 1.0), 1000.0)
    with pytest.raises(ValueError, match="source-to-detector"):
        Detector(10, 10, (1.0, 1.0), float("nan"))
    d = Detector.model().resized(128)
    assert d.size_mm == pytest.approx(Detector.model().size_mm)


def test_centred_and_patient_frames():
    aff = np.array([[-0.5, 0, 0, 100.0], [0, 0.6, 0, -20.0], [0, 0, 2.0, 30.0], [0, 0, 0, 1]])
    vol = Volume(np.zeros((10, 20, 30), np.int16), aff)
    centre_idx = np.array([(30 - 1) / 2, (20 - 1) / 2, (10 - 1) / 2, 1.0])
    assert np.allclose(vol.centre_ras, (aff @ centre_idx)[:3])
    assert np.allclose(vol.ijk_to_centred @ centre_idx, [0, 0, 0, 1])
    T = isopose(C.VIEW_PA)
    T_ras = pose_to_patient(T, aff, vol.shape_ijk)
    assert np.allclose(T_ras[:3, 3], T[:3, 3] + vol.centre_ras)
    assert np.allclose(pose_from_patient(T_ras, aff, vol.shape_ijk), T)
    T_lps = pose_to_patient(T, aff, vol.shape_ijk, space="LPS")
    assert np.allclose(T_lps[:3, 3], np.array([-1, -1, 1]) * T_ras[:3, 3])
