"""One pipeline over two engines: the numpy and torch render kernels agree, the CTA levels are
what they claim, both backends give the same poses at the default settings, and a whole
registration (library and Slicer logic) runs in a process where torch cannot be imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from geopose import contract as C
from geopose.bench.cases import phantom_case
from geopose.cta import save_volume
from geopose.geometry import Detector, isopose
from geopose.geometry import poses as N
from geopose.nets.decoding import select_view
from geopose.options import RegistrationOptions, TTOSchedule
from geopose.register import register_case
from geopose.render.density import hu_to_density
from geopose.render.renderer import NumpyRenderer, TorchRenderer, make_renderer
from geopose.images import block_mean
from geopose.render.volume import RenderVolume
from geopose.resources import default_models_dir
from geopose.volume import Volume

REPO = Path(__file__).resolve().parents[2]
RNG = np.random.default_rng(7)
#: Same answer on either engine (issue 13): poses within these of each other.
ENGINE_AGREEMENT_MM = 0.5
ENGINE_AGREEMENT_DEG = 0.1


def _small_volume() -> tuple[Volume, Volume, Volume]:
    """A 40^3 head-like blob (HU) with a bone shell and a 'vessel' rod, on an oblique grid,
    with its cranium and vessel masks."""
    k, j, i = np.mgrid[:40, :36, :44]
    r = np.sqrt(((i - 22) / 18.0) ** 2 + ((j - 18) / 15.0) ** 2 + ((k - 20) / 17.0) ** 2)
    hu = np.where(r < 1, 40.0, -1000.0) + np.where((r > 0.85) & (r < 1), 900.0, 0.0)
    rod = (abs(i - 20) < 2) & (abs(j - 15) < 2) & (r < 0.8)
    hu = np.where(rod, 300.0, hu).astype(np.float32)
    affine = np.diag([2.0, 2.2, 2.5, 1.0])
    affine[:3, :3] = N.euler_zyx_to_matrix(np.array([0.2, -0.1, 0.05])) @ affine[:3, :3]
    cta = Volume(hu, affine)
    return cta, cta.like((r < 1).astype(np.uint8)), cta.like(rod.astype(np.uint8))


def test_masks_are_made_only_when_a_render_needs_them_and_the_level_gains_them_unchanged():
    """A render of the total density alone builds a level without mask channels and computes no mask (the
    vessel mask from a CTA takes seconds); the first render of a mask channel adds them to that level, its
    total channel and crop unchanged, and every render equals one from a volume built with masks at once."""
    cta, cranium, vessels = _small_volume()
    made = []
    lazy = RenderVolume(cta, {"cranium": lambda: made.append("cranium") or cranium,
                              "vessels": lambda: made.append("vessels") or vessels})
    eager = RenderVolume(cta, {"cranium": cranium, "vessels": vessels})
    pose, det = isopose(C.VIEW_PA), Detector.model().resized(24)
    for engine in ("numpy", "torch"):
        ours, theirs = make_renderer(lazy, engine), make_renderer(eager, engine)
        total = ours.render(pose, det, ("total",))
        if engine == "numpy":
            assert made == [] and not ours.level_for_pose(pose, det, masked=False).masked
        np.testing.assert_array_equal(total, theirs.render(pose, det, ("total",)))
        np.testing.assert_array_equal(ours.render(pose, det, ("total", "cranium", "vessels")),
                                      theirs.render(pose, det, ("total", "cranium", "vessels")))
    assert made == ["cranium", "vessels"]
    for factors, level in lazy.levels.items():
        assert level.masked and level.origin_blocks == eager.level(factors).origin_blocks
        np.testing.assert_array_equal(level.density, eager.level(factors).density)


def test_masks_made_ahead_on_another_thread_are_awaited_and_their_errors_raised_where_asked_for():
    """``make_masks_ahead`` makes each mask once, off the calling thread; the renders of the total density go on
    meanwhile, a render of a mask channel waits for it and equals one from a volume built with the masks; a mask
    that cannot be made raises its own error where it is asked for, not on the other thread."""
    import threading

    from geopose.errors import InputError

    cta, cranium, vessels = _small_volume()
    release, made = threading.Event(), []

    def slow_vessels() -> Volume:
        release.wait(10.0)
        made.append((threading.current_thread().name, threading.current_thread().daemon))
        return vessels

    ahead = RenderVolume(cta, {"cranium": cranium, "vessels": slow_vessels})
    ahead.make_masks_ahead()
    ahead.make_masks_ahead()  # nothing more to start
    pose, det = isopose(C.VIEW_PA), Detector.model().resized(24)
    ours = make_renderer(ahead, "numpy")
    ours.render(pose, det, ("total",))  # does not wait for the vessel mask
    assert made == []
    release.set()
    got = ours.render(pose, det, ("total", "cranium", "vessels"))
    # Not a daemon: an interpreter that exits meanwhile waits for it instead of killing it inside SimpleITK.
    assert made == [("geopose-cta-masks", False)]
    np.testing.assert_array_equal(got, make_renderer(RenderVolume(cta, {"cranium": cranium, "vessels": vessels}), "numpy")
                                  .render(pose, det, ("total", "cranium", "vessels")))

    def no_contrast() -> Volume:
        raise InputError("no vessel in this CT")

    failing = RenderVolume(cta, {"cranium": cranium, "vessels": no_contrast})
    failing.make_masks_ahead()
    assert failing.mask("cranium") is not None
    with pytest.raises(InputError, match="no vessel in this CT"):
        failing.mask("vessels")


def test_levels_are_the_density_block_averaged_and_cropped():
    cta, cranium, vessels = _small_volume()
    volume = RenderVolume(cta, {"cranium": cranium, "vessels": vessels})
    full = volume.level((1, 1, 1))
    density = hu_to_density(cta.array)
    # Cropped to the occupied box plus one empty voxel: same values where it overlaps.
    occupied = np.argwhere(density > 0)
    lo = np.maximum(occupied.min(0) - 1, 0)
    np.testing.assert_allclose(full.density[0], density[lo[0]:lo[0] + full.density.shape[1], lo[1]:lo[1] + full.density.shape[2],
                                                       lo[2]:lo[2] + full.density.shape[3]], atol=1e-6)
    assert full.density[0].sum() == pytest.approx(density.sum(), rel=1e-5)
    assert full.density[2].sum() == pytest.approx((density * vessels.array).sum(), rel=1e-5)
    # The index -> world map still puts every voxel where it was.
    np.testing.assert_allclose(full.ijk_to_world @ [0, 0, 0, 1], cta.ijk_to_centred @ [lo[2], lo[1], lo[0], 1], atol=1e-9)
    coarse = volume.level((2, 2, 2))
    np.testing.assert_allclose(coarse.spacing_mm, 2 * np.asarray(cta.spacing_mm))
    # Block averages keep the line-integral mass (each coarse voxel is 8 x larger).
    assert 8 * coarse.density[0].sum() == pytest.approx(density.sum(), rel=1e-4)
    np.testing.assert_allclose(block_mean(np.arange(12.0).reshape(1, 2, 6), (1, 2, 3)), [[[4.0, 7.0]]])
    # The coarsest level no finer than a voxel size, power-of-two factors; with the option, renders that resolve
    # finer sample the coarsest level with voxels of at most its size (2 x 2.0 mm, 2.2 and 2.5 mm kept: 4.4, 5 > 4).
    assert volume.factors_for(2.1) == (1, 1, 1) and volume.factors_for(4.5) == (2, 2, 1)
    assert RenderVolume(cta, finest_spacing_mm=4.0).factors_for(1.0) == (2, 1, 1)
    assert RenderVolume(cta, finest_spacing_mm=4.0).factors_for(4.5) == volume.factors_for(4.5)


def test_a_coarsened_volume_is_the_cta_on_its_block_grid_in_a_shifted_frame():
    """The block grid of an odd-sized CTA: HU block means, masks kept where they fill half a block, a centred
    frame shifted by the grid centres' offset; a pose moved by that shift renders it much like the CTA's own level."""
    cta, cranium, vessels = _small_volume()
    odd = Volume(cta.array[:39, :35, :43], cta.ijk_to_ras)
    masks = {"cranium": odd.like(cranium.array[:39, :35, :43]), "vessels": odd.like(vessels.array[:39, :35, :43])}
    volume = RenderVolume(odd, masks)
    assert volume.coarsened((1, 1, 1))[0] is volume
    coarse, shift = volume.coarsened((2, 2, 2))
    assert coarse.cta.array.shape == (20, 18, 22)
    np.testing.assert_allclose(coarse.cta.array, block_mean(odd.array, (2, 2, 2)))
    held = block_mean(masks["vessels"].array.astype(np.float32), (2, 2, 2))
    np.testing.assert_array_equal(coarse.mask("vessels"), held >= 0.5)
    assert 0.5 < np.linalg.norm(shift[:3, 3]) < 3.0 and np.allclose(shift[:3, :3], np.eye(3))
    # A block's centre, in the CTA's centred frame and moved by the shift, is that block voxel in the coarse frame.
    blocks = np.array([[0, 0, 0], [7, 3, 12], [19, 17, 21]])
    centres = odd.centred_points(2 * blocks + 0.5)
    np.testing.assert_allclose(coarse.cta.centred_points(blocks), centres + shift[:3, 3], atol=1e-9)
    pose, det = N.pose_from_params(np.array([0.3, 0.1, -0.05]), np.array([4.0, 620.0, -6.0])), Detector(48, 40, (2.0, 2.4), 1020.0)
    ours = TorchRenderer(coarse).render(shift @ pose, det, ("total", "vessels"))
    theirs = TorchRenderer(volume).drr(volume.level((2, 2, 2)))(torch.as_tensor(pose)[None], detector=det, channels=(0, 2))
    theirs = theirs[0].detach().numpy()
    # HU block means under the CTA's density scale, not density block means: alike inside, apart at this synthetic
    # head's sharp air and bone edges (a real CTA's own partial volume brings its scale's floor near air)
    correlation = [np.corrcoef(got.ravel(), want.ravel())[0, 1] for got, want in zip(ours, theirs)]
    assert correlation[0] > 0.85 and correlation[1] > 0.93, correlation


def test_a_ct_finer_than_the_render_grid_is_rendered_on_its_block_means_in_its_own_frame(tmp_path):
    """A CTA finer than ``RENDER_GRID_MM`` is rendered from its block means (as ``sitk.BinShrink``: whole blocks,
    an odd far edge dropped) in that CTA's own centred frame, with the density scale of its full grid; a given mask
    keeps the blocks it fills at least half; the poses need no shift: a block voxel lies where the centre of the
    voxels it averages lies; and a CTA no finer keeps its own grid."""
    from geopose.register.case import prepare_case
    from geopose.render.density import DensityScale
    from geopose.render.volume import render_factors

    cta, cranium, _ = _small_volume()
    fine_affine = cta.ijk_to_ras @ np.diag([0.25, 0.25, 0.25, 1.0])  # 0.5-0.6 mm voxels
    hu = np.repeat(np.repeat(np.repeat(cta.array, 4, 0), 4, 1), 4, 2)[:157, :143, :175]  # odd sizes
    fine = Volume(hu + np.float32(1.0) * (np.arange(175) % 3), fine_affine)
    mask = fine.like(np.repeat(np.repeat(np.repeat(cranium.array, 4, 0), 4, 1), 4, 2)[:157, :143, :175])
    assert render_factors(fine.spacing_mm) == (2, 1, 1) and render_factors(cta.spacing_mm) == (1, 1, 1)
    runs = phantom_case(6010, tmp_path / "runs", 4.0).runs
    case = prepare_case(fine, runs, cranium_mask=mask)
    grid = case.volume.cta
    assert grid.array.shape == (157, 143, 87) and case.volume.scale == DensityScale.of(fine.array)
    np.testing.assert_array_equal(grid.array, fine.shrunk((2, 1, 1)).array)
    np.testing.assert_allclose(case.volume.centred_to_ras, fine.centred_to_ras)
    blocks = np.array([[0, 0, 0], [40, 71, 86], [156, 142, 3]])
    np.testing.assert_allclose(case.volume.centred_points(blocks),
                               (fine.centred_points(blocks * [1, 1, 2]) + fine.centred_points(blocks * [1, 1, 2] + [0, 0, 1])) / 2,
                               atol=1e-9)
    held = (mask.array[:, :, 0:174:2].astype(int) + mask.array[:, :, 1:174:2]) / 2
    np.testing.assert_array_equal(case.volume.mask("cranium"), held >= 0.5)
    assert prepare_case(cta, runs).volume.cta is cta


def test_numpy_and_torch_kernels_render_the_same():
    cta, cranium, vessels = _small_volume()
    volume = RenderVolume(cta, {"cranium": cranium, "vessels": vessels})
    ours, theirs = NumpyRenderer(volume), TorchRenderer(volume)
    det = Detector(48, 40, (2.0, 2.4), 1020.0)
    pose = N.pose_from_params(np.array([0.3, 0.1, -0.05]), np.array([4.0, 620.0, -6.0]))
    want = theirs.render(pose, det, ("total", "cranium", "vessels"))
    got = ours.render(pose, det, ("total", "cranium", "vessels"))
    assert got.shape == want.shape == (3, 48, 40) and want[2].max() > 1.0
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * want.max())
    # Batched poses render like single ones.
    both = ours.render(np.stack((pose, isopose(C.VIEW_PA))), det, ("vessels",))
    np.testing.assert_allclose(both[0], got[2:3], atol=1e-6)
    # render_px: a coarse render resized bilinearly (torch's interpolate, align_corners=False).
    with torch.no_grad():
        level = theirs.level_for_pose(pose, det.resized(24, 20))
        small = theirs.drr(level)(torch.as_tensor(pose)[None], detector=det.resized(24, 20), channels=(0,))
        want_up = F.interpolate(small, size=det.shape, mode="bilinear", align_corners=False)[0].numpy()
    np.testing.assert_allclose(ours.render(pose, det, render_px=24), want_up, rtol=1e-4, atol=1e-4 * want_up.max())
    with pytest.raises(ValueError, match="unknown render channel"):
        ours.render(pose, det, ("bone",))


def test_a_render_samples_the_level_its_pixels_resolve():
    cta, _, _ = _small_volume()
    fine = Volume(np.repeat(np.repeat(np.repeat(cta.array, 2, 0), 2, 1), 2, 2), cta.ijk_to_ras @ np.diag([0.5, 0.5, 0.5, 1]))
    renderer = NumpyRenderer(RenderVolume(fine))
    # The 96-px network render: 3.2 mm pixels at the detector, 2.04 mm at the volume centre; voxels up
    # to 1.5 footprints (3.06 mm): (1.0, 1.1, 1.25) mm voxels double along every axis, not more.
    model = Detector.model().resized(96)
    assert renderer.voxel_per_pixel == 1.5
    assert renderer.level_for_pose(isopose(C.VIEW_PA), model).factors == (2, 2, 2)
    # The 256-px model detector: 0.76 mm footprints, 1.15 mm voxels at most: the CTA's own grid.
    assert renderer.level_for_pose(isopose(C.VIEW_PA), Detector.model()).factors == (1, 1, 1)
    # Greedy Refine and the search may sample up to 3 footprints (6.1 mm): the same volume and kernels, a coarser level.
    estimator = renderer.sampling(3.0)
    assert estimator.level_for_pose(isopose(C.VIEW_PA), model).factors == (4, 4, 4) and renderer.voxel_per_pixel == 1.5
    estimator.render(isopose(C.VIEW_PA), model)
    assert estimator.volume is renderer.volume and (4, 4, 4) in renderer.volume.levels
    assert estimator._kernels is renderer._kernels and len(renderer._kernels) == 1


def test_a_registration_samples_no_finer_level_than_its_tto_images_need(tmp_path):
    """The finest level follows the TTO image size: 2 mm for a CPU's 128 px images, whose 1.5-footprint voxels
    (1.9-2.8 mm) straddle the 2 mm level's bound, the 1 mm render grid for CUDA's 256 px; ``work_spacing_mm`` wins."""
    from geopose.register.engine import finest_level_mm, start_case
    from geopose.register.progress import Monitor

    cta, _, _ = _small_volume()
    fine = Volume(np.repeat(np.repeat(np.repeat(cta.array, 2, 0), 2, 1), 2, 2), cta.ijk_to_ras @ np.diag([0.5, 0.5 / 1.1, 0.4, 1]))
    assert np.allclose(fine.spacing_mm, 1.0)
    runs = phantom_case(6010, tmp_path / "runs", 4.0).runs
    cpu = RegistrationOptions(backend="onnxruntime")
    for options, finest_mm, factors in ((cpu, 2.0, (2, 2, 2)), (cpu.replace(**{"tto.px": 256}), 1.0, (1, 1, 1)),
                                        (cpu.replace(work_spacing_mm=4.0), 4.0, (4, 4, 4))):
        engine, case = start_case(fine, runs, options, None, cranium_mask=None, segmentation=None, dsa_masks=None,
                                  monitor=Monitor())
        assert max(case.views["pa"].tto_detector.shape) == (options.tto.px or 128)
        # Pixel footprints of 1.27 mm (1.9 mm voxels at most): the 1 mm grid, or the option's level.
        assert case.volume.finest_spacing_mm == finest_mm and case.volume.factors_for(1.9) == factors
        assert engine.describe(options, case)["finest_level_mm"] == finest_mm
    assert finest_level_mm(128) == 2.0 and finest_level_mm(256) == 1.0


def test_numpy_view_rule():
    logits = RNG.normal(size=(6, 3))
    lateral = np.array([True, False, True, True, False, False])
    view = select_view(logits, lateral)
    assert all(v == C.VIEW_PA for v, lat in zip(view, lateral) if not lat)
    assert all(v == (C.VIEW_LAT_PLUS if lg[2] > lg[0] else C.VIEW_LAT_MINUS) for v, lg, lat in zip(view, logits, lateral) if lat)
    np.testing.assert_array_equal(select_view(logits, None), logits.argmax(1))


# ------------------------------------------------------------ the two backends


@pytest.fixture(scope="module")
def phantom_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("engines")
    case = phantom_case(5003, folder, spacing_mm=3.0)
    save_volume(case.cranium, folder / "cranium.nii.gz")
    save_volume(case.vessels, folder / "vessels.nii.gz")
    return folder


def _pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mm, deg) between two camera poses: how far apart the CTA centre lies in the two camera frames,
    and the angle between the rotations."""
    centre = [N.invert(p)[:3, 3] for p in (a, b)]  # the world origin in each camera frame
    return float(np.linalg.norm(centre[0] - centre[1])), float(np.degrees(N.rotation_angle_rad(a[:3, :3].T @ b[:3, :3])))


def test_both_backends_give_the_same_registration_at_the_defaults(phantom_folder):
    """torch and onnxruntime + numpy, every option at its default up to the TTO: the same views, the
    same accepted proposals, the same TTO start, and poses within 0.5 mm / 0.1 deg. The TTO itself
    runs through the torch kernel on either backend (it needs gradients), so from one start it is one
    computation; how far its result moves with the start is measured in experiments/tto_schedule/tto_schedule.md."""
    case = phantom_case(5003, phantom_folder, spacing_mm=3.0)
    results = {
        backend: register_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels,
                               options=RegistrationOptions(backend=backend, tto=TTOSchedule(iterations=0)))
        for backend in ("torch", "onnxruntime")
    }
    a, b = results["torch"], results["onnxruntime"]
    assert a.engine["renderer"] == "torch" and b.engine["renderer"] == "numpy" and b.engine["backend"] == "onnxruntime"
    assert a.engine["render_px"] == b.engine["render_px"] == 96
    assert a.registration.chosen_start == b.registration.chosen_start
    for name, score in a.registration.starts.items():
        assert b.registration.starts[name] == pytest.approx(score, abs=2e-3), name
    mm, deg = _pose_gap(a.registration.patient_pose, b.registration.patient_pose)
    assert mm < ENGINE_AGREEMENT_MM and deg < ENGINE_AGREEMENT_DEG, ("patient pose", mm, deg)
    for key in ("pa", "lat"):
        va, vb = a.views[key], b.views[key]
        assert va.init.view == vb.init.view
        assert [p.accepted for p in va.refine.proposals] == [p.accepted for p in vb.refine.proposals]
        for stage in ("init", "refine", "final"):
            mm, deg = _pose_gap(va.stage_poses[stage], vb.stage_poses[stage])
            assert mm < ENGINE_AGREEMENT_MM and deg < ENGINE_AGREEMENT_DEG, (key, stage, mm, deg)
        assert va.quality.flag == vb.quality.flag
        assert va.final_mncc == pytest.approx(vb.final_mncc, abs=1e-3)


# ------------------------------------------------------------ without torch
_BLOCK_TORCH = """
import sys

class _NoTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("PyTorch is blocked in this test process")
        return None

sys.meta_path.insert(0, _NoTorch())
"""

_LIBRARY_RUN = """
import json, sys
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.register import register_case
from geopose.register.record import build_record

folder = sys.argv[1]
cta = load_cta(f"{folder}/cta.nii.gz")
cranium = load_cta(f"{folder}/cranium.nii.gz", check_hu=False)
vessels = load_cta(f"{folder}/vessels.nii.gz", check_hu=False)
runs = {key: read_dsa(f"{folder}/dsa_{key}.dcm") for key in ("pa", "lat")}
seen = []
result = register_case(cta, runs, cranium_mask=cranium, segmentation=vessels,
                       progress=lambda stage, fraction, message: seen.append((stage, message)))
record = build_record(result, runs)
json.dump({"record": record, "seen": seen, "torch_loaded": "torch" in sys.modules}, open(f"{folder}/numpy.json", "w"))
"""


def _run_without_torch(script: str, *args: str) -> None:
    code = _BLOCK_TORCH + textwrap.dedent(script)
    proc = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO / "Logic")},
    )
    assert proc.returncode == 0, proc.stderr[-4000:]


@pytest.mark.parametrize("code, policy, sleeps", [("import torch, geopose", None, False),
                                                   ("import geopose, torch", None, True),
                                                   ("import torch, geopose", "PASSIVE", True)])
def test_idle_openmp_threads_sleep_unless_torch_was_imported_first(code: str, policy: str | None, sleeps: bool):
    """geopose asks OpenMP's idle threads to sleep (two registrations at once on 2 cores took 11x a lone one's time
    with spinning threads); after torch it no longer can, and a registration's notes and record say so."""
    env = {key: value for key, value in os.environ.items() if key != "OMP_WAIT_POLICY"}
    env.update({"PYTHONPATH": str(REPO / "Logic")} | ({"OMP_WAIT_POLICY": policy} if policy else {}))
    script = (f"{code}\nfrom geopose.register.engine import engine_notes\nfrom geopose.register.record import library_versions\n"
              "print(geopose.OPENMP_THREADS_SLEEP, len(engine_notes()), library_versions()['openmp_idle_threads'])")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ([str(sleeps), "0", "sleep"] if sleeps else [str(sleeps), "1", "spin", "(see", "the", "notes)"])


def test_registration_runs_without_torch_and_matches_the_torch_engine(phantom_folder):
    """The default options in a process that cannot import torch: onnxruntime + numpy, the TTO
    skipped and said so, and the same poses as the torch engine without TTO."""
    if not (default_models_dir() / "geopose_init.onnx").is_file():
        pytest.skip("no shipped ONNX models")
    _run_without_torch(_LIBRARY_RUN, str(phantom_folder))
    out = json.loads((phantom_folder / "numpy.json").read_text())
    assert not out["torch_loaded"]
    stages = {stage for stage, _ in out["seen"]}
    assert {"prepare", "calibration", "init", "refine", "tto", "done"} <= stages
    assert any("needs PyTorch" in message for stage, message in out["seen"] if stage == "tto")
    record = out["record"]
    assert record["environment"]["torch"] == "not installed" and "tto_trace" not in record
    assert record["engine"]["backend"] == "onnxruntime" and "skipped" in record["engine"]["tto"]
    assert record["notes"] and "needs PyTorch" in record["notes"][0]

    case = phantom_case(5003, phantom_folder, spacing_mm=3.0)
    result = register_case(case.cta, case.runs, cranium_mask=case.cranium, segmentation=case.vessels,
                           options=RegistrationOptions(backend="torch", tto=TTOSchedule(iterations=0)))
    for key in ("pa", "lat"):
        view = record["views"][key]
        want = result.views[key].final_pose
        mm, deg = _pose_gap(np.asarray(view["pose_centred"]), want)
        assert mm < ENGINE_AGREEMENT_MM and deg < ENGINE_AGREEMENT_DEG, (key, mm, deg)
        assert view["view_label"] == result.views[key].init.view
        assert view["refinement"]["accepted"] == result.views[key].refine.accepted
        assert view["quality"]["flag"] == result.views[key].quality.flag


_SLICER_RUN = """
import json, sys
from geopose import mrml
from geopose.errors import InputError
from geopose.options import RegistrationOptions, TTOSchedule

folder, repo = sys.argv[1], sys.argv[2]
sys.path.insert(0, f"{repo}/Testing/Python")
import slicer_harness

scene = mrml.new_scene()
module = slicer_harness.load_module(slicer_harness.SLICER_TAGS[-1], scene)
logic = module.GeoPoseLogic()
cta = mrml.read_volume_node(scene, f"{folder}/cta.nii.gz", "CTA")
pa, _ = logic.importDSA(f"{folder}/dsa_pa.dcm", "PA", ctaNode=cta)
lat, _ = logic.importDSA(f"{folder}/dsa_lat.dcm", "LAT", ctaNode=cta)
try:
    logic.register(cta=cta, dsaPA=pa, dsaLAT=lat, options=RegistrationOptions(backend="torch"))
    refused = ""
except InputError as exc:
    refused = str(exc)
messages = []
out = logic.register(cta=cta, dsaPA=pa, dsaLAT=lat,
                     options=RegistrationOptions(tto=TTOSchedule(iterations=25), model_clip_percentiles=(2, 98)),
                     progress=lambda s, f, m: messages.append(m))
json.dump({
    "refused": refused,
    "messages": messages,
    "notes": out["record"]["notes"],
    "options": out["record"]["options"],
    "engine": out["record"]["engine"],
    "torch_version": out["record"]["environment"]["torch"],
    "pose_ras": {k: mrml.transform_matrix(out[f"{k}Pose"]).tolist() for k in ("pa", "lat")},
    "record_pose_ras": {k: out["record"]["views"][k]["pose_ras"] for k in ("pa", "lat")},
    "table_rows": out["table"].GetTable().GetNumberOfRows(),
    "torch_loaded": "torch" in sys.modules,
}, open(f"{folder}/slicer.json", "w"))
"""


def test_slicer_logic_without_torch_runs_init_and_refine(phantom_folder):
    pytest.importorskip("slicer", reason="needs the slicer-core wheel (Slicer's MRML in Python)")
    if not (default_models_dir() / "geopose_init.onnx").is_file():
        pytest.skip("no shipped ONNX models")
    _run_without_torch(_SLICER_RUN, str(phantom_folder), str(REPO))
    out = json.loads((phantom_folder / "slicer.json").read_text())
    assert not out["torch_loaded"]
    assert "is not installed: install the PyTorch extension" in out["refused"] and "backend 'onnxruntime'" in out["refused"]
    assert any("needs PyTorch" in m for m in out["messages"])
    assert out["notes"] and "skipped" in out["notes"][0]
    assert out["engine"]["backend"] == "onnxruntime" and out["torch_version"] == "not installed"
    for key in ("pa", "lat"):
        np.testing.assert_allclose(out["pose_ras"][key], out["record_pose_ras"][key], atol=1e-6)
    assert out["table_rows"] == 2
    assert out["options"]["model_clip_percentiles"] == [2.0, 98.0] and out["options"]["tto"]["iterations"] == 25


def test_a_volume_with_a_vessel_subset_equals_one_built_with_it():
    """``RenderVolume.with_vessels`` recomputes only the vessel channel of the levels built so far, from
    the kept voxels: equal to a volume built with that subset as its vessel mask, edge blocks (which
    hold fewer voxels) included, with the CTA array untouched."""
    rng = np.random.default_rng(3)
    hu = rng.normal(0.0, 300.0, (21, 18, 23)).astype(np.float32)
    hu[:2] = -1000.0  # empty slices: the levels are cropped
    cta = Volume(hu.copy(), np.diag([1.1, 0.9, 1.3, 1.0]))
    vessels = rng.random(hu.shape) < 0.2
    keep = (rng.random(hu.shape) < 0.5) & vessels
    volume = RenderVolume(cta, {"vessels": cta.like(vessels.astype(np.uint8))})
    factors = [(1, 1, 1), (2, 2, 2), (4, 2, 8)]
    for f in factors:
        volume.level(f)
    subset = volume.with_vessels(np.argwhere(keep | ~vessels))  # voxels outside the vessel mask are not vessels
    reference = RenderVolume(cta, {"vessels": cta.like(keep.astype(np.uint8))})
    for f in factors:
        a, b = subset.level(f), reference.level(f)
        assert a.density.shape == b.density.shape and np.allclose(a.ijk_to_world, b.ijk_to_world)
        np.testing.assert_allclose(a.density, b.density, atol=1e-6)
        assert a.density[2].sum() < volume.level(f).density[2].sum()
    np.testing.assert_array_equal(cta.array, hu)
    assert subset.mask("vessels").sum() == keep.sum()
    with pytest.raises(ValueError, match="outside the CTA grid"):
        volume.with_vessels(np.argwhere(keep) + [1, 0, 0])
    with pytest.raises(ValueError, match="C order"):
        volume.with_vessels(np.argwhere(keep)[::-1])
