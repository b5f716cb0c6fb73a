"""Rigid algebra, the isopose table of CONVENTIONS.md, DICOM angles, projection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from geopose import contract as C
from geopose.geometry import (
    CArmAngles,
    Detector,
    RigidTransform,
    axis_angle_to_matrix,
    backproject_pixels,
    carm_angles_from_pose,
    euler_zyx_to_matrix,
    isopose,
    matrix_to_axis_angle,
    matrix_to_euler_zyx,
    params_from_pose,
    pose_from_carm_angles,
    pose_from_params,
    pose_to_patient,
    pose_from_patient,
    project_points,
    source_and_detector_points,
    view_from_primary_angle,
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


# The isopose table of CONVENTIONS.md section 2: source, detector centre, row-0 and column-0 directions.
ISOPOSE_TABLE = {
    C.VIEW_PA: ((0, 650, 0), (0, -370, 0), (0, 0, 1), (1, 0, 0)),
    C.VIEW_LAT_PLUS: ((-650, 0, 0), (370, 0, 0), (0, 0, 1), (0, 1, 0)),
    C.VIEW_LAT_MINUS: ((650, 0, 0), (-370, 0, 0), (0, 0, 1), (0, -1, 0)),
}


@pytest.mark.parametrize("view", [C.VIEW_LAT_MINUS, C.VIEW_PA, C.VIEW_LAT_PLUS])
def test_isopose_table(view):
    src_ref, det_ref, row0_dir, col0_dir = (torch.tensor(v, dtype=torch.float64) for v in ISOPOSE_TABLE[view])
    det = Detector.model()
    src, pix = source_and_detector_points(isopose(view, dtype=torch.float64), det)
    assert torch.allclose(src[0], src_ref, atol=1e-9)
    H, W = det.shape
    centre = pix[0, H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].reshape(-1, 3).mean(0)
    assert torch.allclose(centre, det_ref, atol=1e-9)
    # Row 0 lies towards +z; column 0 towards the tabulated direction.
    row_dir = torch.nn.functional.normalize(pix[0, 0, W // 2] - pix[0, -1, W // 2], dim=0)
    col_dir = torch.nn.functional.normalize(pix[0, H // 2, 0] - pix[0, H // 2, -1], dim=0)
    assert torch.allclose(row_dir, row0_dir, atol=1e-9)
    assert torch.allclose(col_dir, col0_dir, atol=1e-9)
    # Detector plane SDD from the source, spacing 1.2 mm.
    assert torch.isclose((centre - src[0]).norm(), torch.tensor(C.MODEL_SDD_MM, dtype=torch.float64))
    assert torch.isclose((pix[0, 0, 0] - pix[0, 0, 1]).norm(), torch.tensor(C.MODEL_PIXEL_SPACING_MM, dtype=torch.float64))


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
        back = carm_angles_from_pose(T, sid_mm=det_sdd)[0]
        assert back.primary_deg == pytest.approx(a, abs=1e-9)
        assert back.secondary_deg == pytest.approx(2.0, abs=1e-9)
        assert back.sod_mm == pytest.approx(720.0)
        src, _ = source_and_detector_points(T, Detector(8, 8, (1.0, 1.0), det_sdd))
        assert src[0].norm().item() == pytest.approx(720.0)
    # Primary 0 / SOD 650 is the PA isopose; -90 (RAO) is LAT-, +90 (LAO) LAT+.
    for a, view in ((0.0, C.VIEW_PA), (-90.0, C.VIEW_LAT_MINUS), (90.0, C.VIEW_LAT_PLUS)):
        T = pose_from_carm_angles(CArmAngles(a, 0.0, C.MODEL_SDD_MM, C.SOURCE_TO_ISOCENTER_MM))
        assert torch.allclose(T.matrix, isopose(view, dtype=torch.float64).matrix, atol=1e-9)
    # Cranial tilt (positive secondary) tilts the real detector towards the head; the model
    # source takes the detector's side, so it moves towards +z (superior).
    T = pose_from_carm_angles(CArmAngles(0.0, 20.0, 1020.0, 650.0))
    src, pix = source_and_detector_points(T, Detector(2, 2, (1.0, 1.0), 1020.0))
    assert src[0, 2] > 100 and pix[0].reshape(-1, 3)[:, 2].mean() < -100


def test_projection_by_hand_and_backprojection():
    det = Detector(rows=100, cols=120, spacing_mm=(0.5, 0.4), sdd_mm=1000.0)
    T = isopose(C.VIEW_PA, dtype=torch.float64)
    # PA: source at y = +650, detector plane at y = -350; magnification 1000/650 at the isocentre.
    pts = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 13.0], [5.0, 325.0, -4.0]], dtype=torch.float64)
    rc, depth = project_points(T, det, pts)
    rc = rc[0]
    cr, cc = (100 - 1) / 2, (120 - 1) / 2
    m = 1000.0 / 650.0
    assert torch.allclose(rc[0], torch.tensor([cr, cc], dtype=torch.float64))
    assert torch.allclose(rc[1], torch.tensor([cr, cc - 10 * m / 0.4], dtype=torch.float64))  # +x -> towards column 0
    assert torch.allclose(rc[2], torch.tensor([cr - 13 * m / 0.5, cc], dtype=torch.float64))  # +z -> towards row 0
    m2 = 1000.0 / 325.0
    assert torch.allclose(rc[3], torch.tensor([cr + 4 * m2 / 0.5, cc - 5 * m2 / 0.4], dtype=torch.float64))
    assert torch.allclose(depth[0, :3], torch.full((3,), 650.0, dtype=torch.float64))
    # Back-projected rays pass through the points.
    src, d = backproject_pixels(T, det, rc[None])
    v = pts - src[0]
    cross = torch.linalg.cross(v, d[0], dim=-1).norm(dim=-1)
    assert cross.max() < 1e-9
    # Principal offset shifts the image.
    det2 = Detector(100, 120, (0.5, 0.4), 1000.0, principal_offset_mm=(4.0, 0.0))
    rc2, _ = project_points(T, det2, pts[:1])
    assert rc2[0, 0, 1] == pytest.approx(cc + 10.0)


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
    T = isopose(C.VIEW_PA, dtype=torch.float64).matrix[0].numpy()
    T_ras = pose_to_patient(T, aff, vol.shape_ijk)
    assert np.allclose(T_ras[:3, 3], T[:3, 3] + vol.centre_ras)
    assert np.allclose(pose_from_patient(T_ras, aff, vol.shape_ijk), T)
    T_lps = pose_to_patient(T, aff, vol.shape_ijk, space="LPS")
    assert np.allclose(T_lps[:3, 3], np.array([-1, -1, 1]) * T_ras[:3, 3])
