"""Pose gradients of the DRR renderer: autograd vs central finite differences.

Small smooth volume (tapered Gaussian blobs, zero at the border), small detector; runs
in a few seconds. The autograd gradient of trilinear ray marching converges to the
true one at first order in the ray step (the interpolant's slope is piecewise
constant), so the tight check uses a step of 1/32 voxel (on a 16x16 detector
the relative error is about 0.2-2.5 % there and up to about 20 % at the default
half-voxel step, where few rays average out the piecewise-constant slopes).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import renderer_common as rc  # noqa: E402

from geopose.geometry import RigidTransform  # noqa: E402
from geopose.render import DRR  # noqa: E402

VOXEL_MM = 8.0
H_RAD, H_MM = 1e-3, 0.1


@pytest.fixture(scope="module")
def setup():
    torch.manual_seed(0)
    volume = rc.smooth_blobs(n=16, spacing_mm=VOXEL_MM)
    detector = rc.model_detector(16)
    names, poses = rc.validation_poses(n_random=2, seed=1)
    return volume, detector, names, poses


def _gradients(volume, detector, pose, step_mm, loss_kind):
    drr = DRR.from_volume(volume, detector, step_mm=step_mm)
    r0, t0 = (x.float() for x in pose.euler_zyx())
    weights = torch.randn(detector.shape, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        target = drr(RigidTransform.from_euler_zyx(r0 + 0.03, t0 + 3.0))[0, 0]

    def render(r, t):
        return drr(RigidTransform.from_euler_zyx(r, t))[0, 0]

    def loss(img):
        if loss_kind == "weighted":
            return (img * weights).mean()
        a = (img - img.mean()) / img.std()
        b = (target - target.mean()) / target.std()
        return -(a * b).mean()

    return rc.autograd_and_fd_gradients(render, loss, r0, t0, H_RAD, H_MM)


@pytest.mark.parametrize("loss_kind", ["weighted", "ncc"])
@pytest.mark.parametrize("pose_index", [1, 2, 4])
def test_autograd_matches_finite_differences(setup, loss_kind, pose_index):
    volume, detector, names, poses = setup
    auto, fd = _gradients(volume, detector, poses[pose_index], VOXEL_MM / 32, loss_kind)
    assert fd.norm() > 1e-6, "finite-difference gradient vanished: the test pose sees no volume"
    rel = float((auto - fd).norm() / fd.norm())
    assert rel < 0.03, f"{names[pose_index]}: autograd {auto.tolist()} vs FD {fd.tolist()} (relative error {rel:.3g})"


@pytest.mark.parametrize("pose_index", [1, 4])
def test_gradient_error_shrinks_with_the_step(setup, pose_index):
    """Convergence: a 16x finer step cuts the autograd-vs-FD error at least 3x."""
    volume, detector, _, poses = setup
    errors = []
    for step in (VOXEL_MM / 2, VOXEL_MM / 32):
        auto, fd = _gradients(volume, detector, poses[pose_index], step, "weighted")
        errors.append(float((auto - fd).norm() / fd.norm()))
    assert errors[1] < errors[0] / 3, errors
