"""Parity of our DRR renderer with DiffDRR 0.6.x on identical volume, pose and detector.

Runs only where DiffDRR imports (the environment made by
``benchmarks/setup_diffdrr_env.sh``: ``.venv-diffdrr/bin/python -m pytest
Testing/Python/test_render_diffdrr.py``); skipped elsewhere. The full-size comparison
is ``benchmarks/compare_diffdrr.py`` (docs/renderer_validation.md).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("diffdrr.drr", reason="DiffDRR is not installed here (see benchmarks/setup_diffdrr_env.sh)")

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import renderer_common as rc  # noqa: E402

from geopose.geometry import RigidTransform, project_points_tensor  # noqa: E402
from geopose.render import DRR, hu_to_density  # noqa: E402

NCC_MIN = 0.995
POINT_TOL_PX = 0.5


@pytest.fixture(scope="module")
def scene():
    torch.set_num_threads(2)
    volume = rc.head_phantom(n=64, spacing_mm=3.0)
    detector = rc.model_detector(64)
    names, poses = rc.validation_poses(n_random=3, seed=2)
    return volume, detector, names, poses


def test_density_matches_diffdrr_transform(scene):
    volume, detector, _, _ = scene
    ours = torch.as_tensor(hu_to_density(np.ascontiguousarray(volume.array)))
    theirs = rc.DiffDRRAdapter(volume, detector).density_kji()
    assert torch.allclose(ours, theirs, atol=1e-6)


def test_images_match_trilinear(scene):
    volume, detector, names, poses = scene
    ours = DRR.from_volume(volume, detector)
    theirs = rc.DiffDRRAdapter(volume, detector, renderer="trilinear")
    with torch.no_grad():
        for b, name in enumerate(names):
            a, d = ours(poses[b])[0, 0], theirs(poses[b])[0, 0]
            assert d.abs().sum() > 0, f"{name}: DiffDRR image is empty"
            score = rc.ncc(a, d)
            assert score >= NCC_MIN, f"{name}: NCC {score:.5f} vs DiffDRR trilinear"
            # Same units (density x mm): mean intensities agree to 1 %.
            assert abs(float(a.mean() / d.mean()) - 1) < 0.01, name


def test_images_as_close_to_siddon_as_diffdrr_trilinear(scene):
    """Siddon (nearest voxel) differs from any trilinear renderer on this coarse 3 mm grid;
    ours must be as close to it as DiffDRR's own trilinear renderer."""
    volume, detector, names, poses = scene
    ours = DRR.from_volume(volume, detector)
    tri = rc.DiffDRRAdapter(volume, detector, renderer="trilinear")
    sid = rc.DiffDRRAdapter(volume, detector, renderer="siddon")
    with torch.no_grad():
        for b, name in enumerate(names):
            a, t, s = ours(poses[b])[0, 0], tri(poses[b])[0, 0], sid(poses[b])[0, 0]
            assert rc.ncc(a, s) >= rc.ncc(t, s) - 1e-3, f"{name}: NCC to Siddon {rc.ncc(a, s):.5f} vs {rc.ncc(t, s):.5f}"
            assert rc.ncc(a, s) > 0.98, name
            assert abs(float(a.mean() / s.mean()) - 1) < 0.02, name


def test_projected_points_match(scene):
    volume, detector, _, poses = scene
    pts = (torch.rand(20, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5) * 160
    pts = pts.expand(len(poses), -1, -1)
    ours, _ = project_points_tensor(poses, detector, pts)
    theirs = rc.DiffDRRAdapter(volume, detector).project(poses, pts).double()
    err = (ours - theirs).norm(dim=-1)
    assert float(err.max()) < POINT_TOL_PX


def test_bead_centroid_matches(scene):
    _, detector, names, poses = scene
    vol = rc.bead_volume(n=48, spacing_mm=2.0, sigma_mm=3.0)
    ours = DRR.from_volume(vol, detector)
    theirs = rc.DiffDRRAdapter(vol, detector)
    centre = torch.tensor(vol.metadata["centre_mm"], dtype=torch.float64)
    with torch.no_grad():
        for b, name in enumerate(names):
            ca = rc.intensity_centroid(ours(poses[b])[0, 0])
            cd = rc.intensity_centroid(theirs(poses[b])[0, 0])
            proj = project_points_tensor(poses[b], detector, centre[None])[0][0, 0].tolist()
            assert np.hypot(*np.subtract(ca, cd)) < 0.05, f"{name}: centroid {ca} vs DiffDRR {cd}"
            assert np.hypot(*np.subtract(ca, proj)) < POINT_TOL_PX, f"{name}: centroid {ca} vs projection {proj}"


def test_pose_gradient_matches_diffdrr(scene):
    volume, detector, names, poses = scene
    ours = DRR.from_volume(volume, detector)
    theirs = rc.DiffDRRAdapter(volume, detector)
    for b in (1, 3):
        r0, t0 = (x.float() for x in poses[b].euler_zyx())
        with torch.no_grad():
            target = theirs.render_params(r0 + 0.02, t0 + 2.0)[0, 0]
        grads = []
        for render in (lambda r, t: ours(RigidTransform.from_euler_zyx(r, t)), theirs.render_params):
            r, t = r0.clone().requires_grad_(True), t0.clone().requires_grad_(True)
            img = render(r, t)[0, 0]
            a = (img - img.mean()) / img.std()
            c = (target - target.mean()) / target.std()
            (-(a * c).mean()).backward()
            grads.append(torch.cat((r.grad[0], t.grad[0])))
        cos = float(torch.nn.functional.cosine_similarity(*grads, dim=0))
        assert cos > 0.99, f"{names[b]}: gradient cosine {cos:.4f} (ours {grads[0].tolist()}, DiffDRR {grads[1].tolist()})"
