"""The torch DRR kernel against analytic line integrals and the projection model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from geopose import contract as C
from geopose.geometry import Detector, RigidTransform, isopose, project_points
from geopose.render import DRR, hu_to_density, label_channels
from geopose.volume import Volume


def _iso(*views: int) -> torch.Tensor:
    """Isoposes ``(B, 4, 4)`` as a torch batch."""
    return torch.as_tensor(np.stack([isopose(v) for v in views]))


def _grid(n: int, spacing: float = 1.0) -> tuple[torch.Tensor, np.ndarray]:
    """Centred coordinates (mm) of an n^3 grid and its ijk->centred affine."""
    aff = np.diag([spacing, spacing, spacing, 1.0])
    aff[:3, 3] = -spacing * (n - 1) / 2
    x = (torch.arange(n, dtype=torch.float32) - (n - 1) / 2) * spacing
    return x, aff


def test_central_ray_through_sphere_equals_chord():
    n, radius = 96, 30.0
    x, aff = _grid(n)
    zz, yy, xx = torch.meshgrid(x, x, x, indexing="ij")
    sphere = ((xx**2 + yy**2 + zz**2) <= radius**2).float()
    det = Detector(rows=33, cols=33, spacing_mm=(2.0, 2.0), sdd_mm=C.MODEL_SDD_MM)
    img = DRR(sphere, aff, det, step_mm=0.25)(_iso(C.VIEW_PA))[0, 0]
    assert img[16, 16].item() == pytest.approx(2 * radius, rel=0.02)
    # An off-axis ray at lateral offset d through the isocentre plane: chord 2 sqrt(R^2 - d^2).
    m = C.MODEL_SDD_MM / C.SOURCE_TO_ISOCENTER_MM
    d = 10 * 2.0 / m  # ten pixels off centre, at the isocentre
    assert img[16, 26].item() == pytest.approx(2 * math.sqrt(radius**2 - d**2), rel=0.03)


def test_constant_cube_and_batched_poses_match_single():
    n = 40
    _, aff = _grid(n, spacing=2.0)
    vol = torch.ones(n, n, n)
    det = Detector(rows=16, cols=16, spacing_mm=(1.0, 1.0), sdd_mm=C.MODEL_SDD_MM)
    drr = DRR(vol, aff, det, step_mm=0.5)
    poses = _iso(0, 1, 2)
    batch = drr(poses)
    assert batch.shape == (3, 1, 16, 16)
    # Voxel box is 80 mm; zero padding trims a quarter voxel at each face (trilinear).
    assert batch[1, 0, 8, 8].item() == pytest.approx(80.0 - 0.25 * 2.0 * 2, rel=0.01)
    for b in range(3):
        single = drr(poses[b : b + 1])
        assert torch.allclose(single[0], batch[b], atol=1e-4)


def test_bead_appears_where_projected():
    n = 64
    x, aff = _grid(n)
    zz, yy, xx = torch.meshgrid(x, x, x, indexing="ij")
    centre = torch.tensor([12.0, -5.0, 9.0])
    bead = torch.exp(-((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 + (zz - centre[2]) ** 2) / (2 * 1.5**2))
    det = Detector(rows=96, cols=96, spacing_mm=(1.0, 1.0), sdd_mm=1100.0)
    pose = RigidTransform.from_euler_zyx(torch.tensor([[0.35, 0.1, -0.2]]), torch.tensor([[4.0, 640.0, -6.0]]))
    img = DRR(bead, aff, det, step_mm=0.5)(pose)[0, 0]
    rr, cc = torch.meshgrid(torch.arange(96.0), torch.arange(96.0), indexing="ij")
    w = img / img.sum()
    centroid = torch.stack(((w * rr).sum(), (w * cc).sum()))
    expected, _ = project_points(pose.matrix[0].double().numpy(), det, centre[None].double().numpy())
    np.testing.assert_allclose(centroid.numpy(), expected[0], atol=0.2)


def test_label_channels_split_total():
    g = torch.Generator().manual_seed(3)
    dens = torch.rand(20, 22, 24, generator=g)
    labels = torch.randint(0, 4, (20, 22, 24), generator=g)
    stack, names = label_channels(dens, labels, {"cranium": [1, 2], "vessels": [3], "rest": [0]})
    assert names == ["total", "cranium", "vessels", "rest"]
    _, aff = _grid(22)
    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    det = Detector(rows=12, cols=12, spacing_mm=(2.0, 2.0), sdd_mm=1020.0)
    img = DRR(stack, aff, det)(_iso(1))
    assert torch.allclose(img[:, 1:].sum(1), img[:, 0], rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="label map shape"):
        label_channels(dens, labels[:-1], {"x": [1]})


def test_hu_to_density_rule():
    hu = np.array([-1000.0, -900.0, -800.0, -500.0, 0.0, 350.0, 1000.0], dtype=np.float32)
    d = hu_to_density(hu)
    # air -> soft-tissue minimum (-500 here) -> 0; bone kept (factor 1); min-max to [0, 1].
    expected = (np.array([-500, -500, -500, -500, 0, 350, 1000.0]) + 500) / 1500
    assert np.allclose(d, expected, atol=1e-6)
    d2 = hu_to_density(hu, bone_factor=2.0)
    assert d2[-1] == pytest.approx(1.0) and d2[-2] == pytest.approx(850 / 2500)


def test_from_volume_uses_affine_and_labels():
    n = 32
    aff = np.diag([-2.0, 2.0, 3.0, 1.0])  # i runs towards -x (LPS-like storage)
    aff[:3, 3] = (50, -40, 10)
    arr = np.full((n, n, n), -1000, np.int16)
    arr[10:20, 5:12, 20:30] = 1000  # a bone block at i 20..29, j 5..11, k 10..19
    cta = Volume(arr, aff)
    labels = cta.like((arr > 0).astype(np.uint8))
    drr = DRR.from_volume(cta, Detector(64, 64, (2.0, 2.0), 1020.0), labels=labels, label_groups={"bone": [1]})
    img = drr(_iso(C.VIEW_PA))[0]
    assert img.shape == (2, 64, 64)
    assert torch.allclose(img[0], img[1], atol=1e-4)  # all density sits in the bone label
    # The block's centre, in the centred frame, projects onto the image's bright centroid.
    ijk = np.array([24.5, 8.0, 14.5, 1.0])
    centre = (cta.ijk_to_centred @ ijk)[:3]
    expected, _ = project_points(isopose(C.VIEW_PA), drr.detector, centre[None])
    rr, cc = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    w = img[0] / img[0].sum()
    centroid = torch.stack(((w * rr).sum(), (w * cc).sum())).double()
    np.testing.assert_allclose(centroid.numpy(), expected[0], atol=0.5)


def test_gradient_reaches_pose_and_volume():
    n = 24
    x, aff = _grid(n, 2.0)
    zz, yy, xx = torch.meshgrid(x, x, x, indexing="ij")
    blob = torch.exp(-(xx**2 + (yy - 3) ** 2 + zz**2) / 200.0)
    det = Detector(16, 16, (3.0, 3.0), 1020.0)
    r = torch.zeros(1, 3, requires_grad=True)
    t = torch.tensor([[2.0, 650.0, 1.0]], requires_grad=True)
    drr = DRR(blob.clone().requires_grad_(), aff, det)
    img = drr(RigidTransform.from_euler_zyx(r, t))
    (img * torch.linspace(0, 1, 16)).sum().backward()
    assert r.grad.abs().sum() > 0 and t.grad.abs().sum() > 0
    assert drr.density.grad is not None and drr.density.grad.abs().sum() > 0


@pytest.mark.gpu
def test_cuda_matches_cpu():
    n = 48
    x, aff = _grid(n, 2.0)
    zz, yy, xx = torch.meshgrid(x, x, x, indexing="ij")
    vol = torch.exp(-(xx**2 + yy**2 + zz**2) / 400.0)
    det = Detector(32, 32, (2.0, 2.0), 1020.0)
    pose = _iso(0, 1)
    cpu = DRR(vol, aff, det)(pose)
    gpu = DRR(vol.cuda(), aff, det)(pose.to("cuda")).cpu()
    assert torch.allclose(cpu, gpu, rtol=1e-3, atol=1e-3)


def test_both_kernels_count_the_same_work_inside_a_counting_block_only():
    """render.work: renders, rays (pixels) and ray points (rays x samples per ray x channels), counted by
    either kernel only while a block is open; the two kernels march the same samples."""
    from conftest import blob_renderer
    from geopose.render.renderer import TorchRenderer
    from geopose.render.work import counting

    numpy_renderer = blob_renderer()
    torch_renderer = TorchRenderer(numpy_renderer.volume)
    detector, pose = Detector.model().resized(32), isopose(C.VIEW_PA)
    numpy_renderer.render(pose, detector)  # no block open: not counted anywhere
    counts = []
    for renderer in (numpy_renderer, torch_renderer):
        with counting() as work:
            renderer.render(np.stack([pose, pose]), detector, ("total", "cranium"))
        counts.append((work.renders, work.rays, work.points))
        samples = work.points // (work.rays * 2)
        assert work.renders == 2 and work.rays == 2 * 32 * 32 and work.points == work.rays * 2 * samples
        assert samples > 10  # a 192 mm wide volume crossed in steps of a few mm
        assert work.as_dict(0.5)["ns_per_point"] == pytest.approx(5e8 / work.points, rel=1e-3)
    assert counts[0] == counts[1]
