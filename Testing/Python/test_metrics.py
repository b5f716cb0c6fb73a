"""Similarity, Dice, mPCD, clDice, pose-error and view-accuracy metrics on hand-made cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from register_helpers import RIG, _rotation

from geopose.contract import MNCC_PATCH_PX, MODEL_SDD_MM
from geopose.geometry.detector import AP_REORIENT
from geopose.geometry.poses import isopose, pose_from_params
from geopose.metrics import (
    cldice,
    double_geodesic_mm,
    generalized_dice_loss,
    mask_points,
    mpcd,
    pose_errors,
    skeletonize,
    view_accuracy,
)
from geopose.metrics import similarity as S
from geopose.metrics.losses import local_ncc_similarity as local_ncc
from geopose.metrics.losses import mncc_similarity as mncc
from geopose.metrics.losses import ncc_similarity as ncc
from geopose.metrics.measures import pose_error_components


def smooth_image(batch: int = 2, size: int = 48, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, 1, size // 4, size // 4, generator=gen)
    return torch.nn.functional.interpolate(x, size=(size, size), mode="bilinear", align_corners=False) + 0.05 * torch.rand(
        batch, 1, size, size, generator=gen
    )


def minmax64(x: torch.Tensor) -> torch.Tensor:
    x = x.double()
    low, high = x.amin(dim=(-2, -1), keepdim=True), x.amax(dim=(-2, -1), keepdim=True)
    return (x - low) / (high - low)


def brute_force_local_ncc(a: torch.Tensor, b: torch.Tensor, p: int, eps: float = 1e-5) -> torch.Tensor:
    """float64 patch-by-patch mean NCC of the min-max normalised images."""
    a, b = minmax64(a), minmax64(b)
    pa = a.unfold(2, p, 1).unfold(3, p, 1).reshape(a.shape[0], -1, p * p).double()
    pb = b.unfold(2, p, 1).unfold(3, p, 1).reshape(b.shape[0], -1, p * p).double()
    za = (pa - pa.mean(-1, keepdim=True)) / torch.sqrt(pa.var(-1, unbiased=False, keepdim=True) + eps)
    zb = (pb - pb.mean(-1, keepdim=True)) / torch.sqrt(pb.var(-1, unbiased=False, keepdim=True) + eps)
    return (za * zb).mean(-1).mean(-1)


# --------------------------------------------------------------------- NCC
def test_ncc_identity_negative_and_affine():
    x = smooth_image()
    assert torch.allclose(ncc(x, x), torch.ones(2), atol=1e-3)
    assert torch.allclose(ncc(x, -x), -torch.ones(2), atol=1e-3)
    assert torch.allclose(mncc(x, 3.0 * x + 7.0), torch.ones(2), atol=1e-3)
    assert torch.allclose(mncc(x, -2.0 * x + 1.0), -torch.ones(2), atol=1e-3)
    other = smooth_image(seed=5)
    assert (mncc(x, other).abs() < 0.5).all()


@pytest.mark.parametrize("scale, offset", [(1.0, 0.0), (300.0, 2000.0)])
def test_local_ncc_matches_explicit_patches(scale, offset):
    """Also for DRR-like magnitudes, where float32 E[x^2] - E[x]^2 would cancel."""
    a, b = smooth_image(size=32), smooth_image(size=32, seed=3)
    ref = brute_force_local_ncc(a, b, MNCC_PATCH_PX)
    a, b = a * scale + offset, b * scale + offset
    assert torch.allclose(local_ncc(a, b).double(), ref, atol=1e-4)
    assert torch.allclose(mncc(a, b).double(), 0.5 * ncc(a, b).double() + 0.5 * ref, atol=1e-4)
    # On the min-max scale: same values as for the normalised images.
    assert torch.allclose(ncc(a, b).double(), ncc(minmax64(a), minmax64(b)), atol=1e-5)


def test_local_ncc_is_local():
    """Different affine intensity maps per half: every patch inside a half scores 1, the global NCC does not."""
    x = smooth_image(batch=1, size=64)
    y = x.clone()
    y[..., 32:] = 5.0 * y[..., 32:] + 3.0
    inside = 2 * (32 - MNCC_PATCH_PX + 1)  # patches entirely within one half
    total = 64 - MNCC_PATCH_PX + 1
    assert ncc(x, y).item() < 0.6
    assert local_ncc(x, y).item() >= (inside - (total - inside)) / total - 1e-3
    assert local_ncc(x, y).item() > ncc(x, y).item() + 0.2


def test_mncc_is_differentiable_and_batched():
    x = smooth_image()
    y = smooth_image(seed=9).requires_grad_(True)
    score = mncc(x, y)
    assert score.shape == (2,)
    score.sum().backward()
    assert torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="same shape"):
        ncc(x, x[:, :, :10])
    with pytest.raises(ValueError, match="smaller than"):
        local_ncc(x[..., :8, :8], x[..., :8, :8])


# ------------------------------------------------------------------- Dice
def test_generalized_dice_loss_known_values():
    target = torch.zeros(1, 1, 10, 10)
    target[..., 2:6, 2:6] = 1
    assert generalized_dice_loss(target, target).item() == pytest.approx(0.0, abs=1e-6)
    assert generalized_dice_loss(1 - target, target).item() == pytest.approx(1.0, abs=1e-6)
    half = torch.zeros_like(target)
    half[..., 2:6, 4:8] = 1  # 8 of 16 pixels overlap, same size
    assert generalized_dice_loss(half, target, with_background=False).item() == pytest.approx(0.5, abs=1e-6)
    # Two classes weighted by 1/count^2: fg 16 px (8 overlap), bg 84 px (76 overlap).
    w_fg, w_bg = 1 / 16**2, 1 / 84**2
    expected = 1 - 2 * (w_fg * 8 + w_bg * 76) / (w_fg * 32 + w_bg * 168)
    assert generalized_dice_loss(half, target).item() == pytest.approx(expected, rel=1e-5)
    soft = torch.full_like(target, 0.5).requires_grad_(True)
    generalized_dice_loss(soft, target).sum().backward()
    assert soft.grad[..., 3, 3] < 0 < soft.grad[..., 0, 0]  # raise inside, lower outside


# ------------------------------------------------------------------- mPCD
def test_mpcd_shifted_line():
    line = np.stack([np.full(50, 20.0), np.arange(10, 60, dtype=float)], axis=1)
    shifted = line + np.array([3.0, 0.0])
    result = mpcd(shifted, line, spacing_mm=(0.3, 0.5), sod_mm=750.0, sdd_mm=1200.0)
    assert result.px == pytest.approx(3.0)
    assert result.detector_mm == pytest.approx(0.9)
    assert result.isocentre_mm == pytest.approx(0.9 * 750 / 1200)
    # Column shift along the line: only the 3 overhanging end points move away (1, 2, 3 px).
    along = mpcd(line + np.array([0.0, 3.0]), line, spacing_mm=0.5, sod_mm=700.0, sdd_mm=1000.0)
    assert along.px == pytest.approx((1 + 2 + 3) / 50)
    assert along.detector_mm == pytest.approx(0.5 * 6 / 50)


def test_mpcd_from_masks_and_bad_input():
    mask = np.zeros((30, 30), bool)
    mask[10, 5:25] = True
    moved = np.roll(mask, 4, axis=0)
    assert mpcd(mask_points(moved), mask_points(mask), 1.2, 650.0, 1020.0).detector_mm == pytest.approx(4.8)
    with pytest.raises(ValueError, match="empty"):
        mpcd(np.zeros((0, 2)), mask_points(mask), 1.0, 650.0, 1020.0)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        mpcd(np.zeros((5, 3)), mask_points(mask), 1.0, 650.0, 1020.0)
    with pytest.raises(ValueError, match="SOD"):
        mpcd(mask_points(mask), mask_points(mask), 1.0, 1100.0, 1020.0)


# ----------------------------------------------------------------- clDice
def test_skeleton_of_thick_line_is_thin():
    mask = np.zeros((20, 40), bool)
    mask[8:13, 5:35] = True
    skel = skeletonize(mask)
    assert skel.any() and (skel <= mask).all()
    assert skel.sum(axis=0).max() == 1  # one pixel per column
    assert skel.sum() >= 20


def test_cldice_identical_disjoint_and_partial():
    a = np.zeros((40, 40), bool)
    a[10:13, 5:35] = True
    assert cldice(a, a) == pytest.approx(1.0)
    b = np.zeros_like(a)
    b[25:28, 5:35] = True
    assert cldice(a, b) == 0.0
    assert cldice(np.zeros_like(a), a) == 0.0
    half = np.zeros_like(a)
    half[10:13, 5:20] = True
    # Prediction is a sub-segment: precision 1, sensitivity about 1/2 -> clDice about 2/3.
    assert cldice(half, a) == pytest.approx(2 / 3, abs=0.08)
    with pytest.raises(ValueError, match="reference vessel mask is empty"):
        cldice(a, np.zeros_like(a))
    with pytest.raises(ValueError, match="shape"):
        cldice(a, a[:10])


# ------------------------------------------------------------ pose errors
def test_pose_errors_known_rotation_and_translation():
    ref = isopose(1)
    pred = pose_from_params(np.array([0.1, 0.0, 0.0]), np.array([3.0, 646.0, 0.0]))
    err = pose_errors(pred, ref)
    assert err.rotation_deg[0] == pytest.approx(math.degrees(0.1))
    np.testing.assert_allclose(err.euler_deg, [[math.degrees(0.1), 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(err.translation_mm, [[3.0, -4.0, 0.0]], atol=1e-9)
    assert err.translation_norm_mm[0] == pytest.approx(5.0)
    source = pred[:3, 3]  # source position = R @ t
    assert err.source_distance_mm[0] == pytest.approx(np.linalg.norm(source - ref[:3, 3]))
    expected = math.hypot(MODEL_SDD_MM / 2 * 0.1, err.source_distance_mm[0])
    assert err.double_geodesic_mm[0] == pytest.approx(expected)
    assert double_geodesic_mm(ref, ref)[0] == pytest.approx(0.0, abs=1e-9)


def test_pose_errors_wrap_euler_and_validate():
    a = pose_from_params(np.array([math.pi - 0.05, 0.0, 0.0]), np.zeros(3))
    b = pose_from_params(np.array([-math.pi + 0.05, 0.0, 0.0]), np.zeros(3))
    err = pose_errors(a, b)
    assert err.euler_deg[0, 0] == pytest.approx(-math.degrees(0.1), abs=1e-3)
    assert err.rotation_deg[0] == pytest.approx(math.degrees(0.1), abs=1e-3)
    with pytest.raises(ValueError, match="poses"):
        pose_errors(np.eye(3), np.eye(4))


def test_numpy_ncc_family_equals_the_differentiable_one():
    a, b = smooth_image(seed=3).double(), smooth_image(seed=4).double()
    for ours, theirs in ((S.ncc, ncc), (S.local_ncc, local_ncc), (S.mncc, mncc)):
        want = theirs(a, b).numpy()
        got = [ours(a[i, 0].numpy(), b[i, 0].numpy()) for i in range(len(a))]
        np.testing.assert_allclose(got, want, atol=1e-9)
    with pytest.raises(ValueError, match="same shape"):
        S.mncc(a[0, 0].numpy(), b[0, 0, :-1].numpy())


def test_an_mncc_target_scores_as_mncc_bit_for_bit():
    """Greedy Refine and the search score many renders against one target with its terms computed once: each score
    must be ``mncc``'s exactly (a decision there flips on 1e-3), constant images and every patch included."""
    a, b = smooth_image(seed=5).double().numpy(), smooth_image(seed=6).double().numpy()
    target = S.MNCCTarget(a[0, 0])
    images = [b[i, 0] for i in range(len(b))] + [a[0, 0], np.full_like(a[0, 0], 3.0), 2.0 * a[0, 0] + b[0, 0]]
    for image in images:
        assert target(image) == S.mncc(a[0, 0], image)
    assert target(a[0, 0]) == pytest.approx(1.0, abs=1e-3) and target(images[-2]) == pytest.approx(0.0, abs=1e-6)
    assert S.MNCCTarget(np.zeros((20, 20)))(a[0, 0, :20, :20]) == S.mncc(np.zeros((20, 20)), a[0, 0, :20, :20])
    with pytest.raises(ValueError, match="same shape"):
        target(b[0, 0, :-1])
    with pytest.raises(ValueError, match="patch"):
        S.MNCCTarget(np.ones((8, 30)))


def test_view_accuracy():
    assert view_accuracy(np.array([0, 1, 2, 2]), np.array([0, 1, 1, 2])) == 0.75
    assert view_accuracy([1], [1]) == 1.0
    with pytest.raises(ValueError, match="0..2"):
        view_accuracy([3], [1])
    with pytest.raises(ValueError, match="same non-zero number"):
        view_accuracy([0, 1], [1])


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
    # CTA centre swings in the image plane, not in depth). Tilt it 3 deg about its image x axis through
    # the source: out-of-plane rotation only.
    for axis, deg, expected in ((cam[:3, 2], 4.0, {"in_plane_rotation_deg": 4.0, "out_of_plane_rotation_deg": 0.0, "depth_mm": 0.0}),
                                (cam[:3, 0], 3.0, {"out_of_plane_rotation_deg": 3.0, "in_plane_rotation_deg": 0.0})):
        turned = true.copy()
        turned[:3, :3] = _rotation(axis, deg) @ true[:3, :3]
        parts = pose_error_components(turned, true)
        for name, value in expected.items():
            assert parts[name] == pytest.approx(value, abs=1e-6), (deg, name, parts)
