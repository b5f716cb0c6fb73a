"""The inference path without PyTorch: numpy twins agree with the torch originals, and a
whole registration (library and Slicer logic) runs in a process where torch cannot be imported."""

from __future__ import annotations

import json
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
from geopose.geometry import CArmAngles, Detector, RigidTransform, isopose, pose_from_carm_angles, project_points
from geopose.geometry import numpy_poses as N
from geopose.geometry import params_from_pose, source_and_detector_points
from geopose.metrics import mncc
from geopose.metrics import numpy_similarity
from geopose.nets import (
    decode_init_pose, make_predictors, mirror_averaged_logits, normalize_minmax, residual_from_raw, select_view,
)
from geopose.nets import onnx_runtime
from geopose.register import RegistrationOptions, register_case
from geopose.register.case import LABEL_GROUPS
from geopose.render import DRR
from geopose.render.numpy_drr import NumpyDRR, resize_bilinear
from geopose.resources import default_models_dir
from geopose.volume import Volume

REPO = Path(__file__).resolve().parents[2]
RNG = np.random.default_rng(7)


# ------------------------------------------------------------------ numpy twins
def test_pose_algebra_matches_torch():
    r, t = RNG.normal(size=(5, 3)), RNG.normal(size=(5, 3)) * 50
    for rotation in ("euler_zyx", "axis_angle"):
        want = (RigidTransform.from_euler_zyx if rotation == "euler_zyx" else RigidTransform.from_axis_angle)(
            torch.as_tensor(r), torch.as_tensor(t)
        ).matrix.numpy()
        got = N.pose_from_params(r, t, rotation=rotation)
        np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_allclose(N.invert(got), RigidTransform(torch.as_tensor(got)).inverse().matrix.numpy(), atol=1e-12)
    r_back, t_back = N.params_from_pose(N.pose_from_params(r, t))
    want_r, want_t = params_from_pose(torch.as_tensor(N.pose_from_params(r, t)))
    np.testing.assert_allclose(r_back, want_r.numpy(), atol=1e-12)
    np.testing.assert_allclose(t_back, want_t.numpy(), atol=1e-9)
    for view in (C.VIEW_LAT_MINUS, C.VIEW_PA, C.VIEW_LAT_PLUS):
        np.testing.assert_allclose(N.isopose(view), isopose(view, dtype=torch.float64).matrix[0].numpy(), atol=1e-12)
    angles = CArmAngles(-37.0, 12.0, 1150.0, 760.0, roll_deg=2.0, offset_mm=(4.0, -3.0))
    np.testing.assert_allclose(N.pose_from_carm_angles(angles), pose_from_carm_angles(angles).matrix[0].numpy(), atol=1e-12)
    assert N.rotation_angle_rad(N.pose_from_params(np.array([0.3, 0.0, 0.0]), np.zeros(3))[:3, :3]) == pytest.approx(0.3)


def test_projection_matches_torch():
    det = Detector(30, 40, (1.1, 0.9), 1100.0, principal_offset_mm=(3.0, -2.0))
    pose = N.pose_from_params(np.array([0.4, -0.1, 0.2]), np.array([5.0, 700.0, -8.0]))
    src, pix = N.source_and_detector_points(pose, det)
    src_t, pix_t = source_and_detector_points(torch.as_tensor(pose)[None], det)
    np.testing.assert_allclose(src, src_t[0].numpy(), atol=1e-9)
    np.testing.assert_allclose(pix, pix_t[0].numpy(), atol=1e-9)
    points = RNG.normal(size=(20, 3)) * 40
    rc, depth = N.project_points(pose, det, points)
    rc_t, depth_t = project_points(torch.as_tensor(pose)[None], det, torch.as_tensor(points))
    np.testing.assert_allclose(rc, rc_t[0].numpy(), atol=1e-9)
    np.testing.assert_allclose(depth, depth_t[0].numpy(), atol=1e-9)


def _small_volume() -> tuple[Volume, Volume]:
    """A 40^3 head-like blob (HU) with a bone shell and a 'vessel' rod, on an oblique grid."""
    k, j, i = np.mgrid[:40, :36, :44]
    r = np.sqrt(((i - 22) / 18.0) ** 2 + ((j - 18) / 15.0) ** 2 + ((k - 20) / 17.0) ** 2)
    hu = np.where(r < 1, 40.0, -1000.0) + np.where((r > 0.85) & (r < 1), 900.0, 0.0)
    rod = (abs(i - 20) < 2) & (abs(j - 15) < 2) & (r < 0.8)
    hu = np.where(rod, 300.0, hu).astype(np.float32)
    affine = np.diag([2.0, 2.2, 2.5, 1.0])
    affine[:3, :3] = N.euler_zyx_to_matrix(np.array([0.2, -0.1, 0.05])) @ affine[:3, :3]
    cta = Volume(hu, affine)
    labels = cta.like(((r < 1) * 1 + rod * 2).astype(np.uint8))
    return cta, labels


def test_numpy_renderer_matches_torch():
    cta, labels = _small_volume()
    det = Detector(48, 40, (2.0, 2.4), 1020.0)
    drr_t = DRR.from_volume(cta, det, labels=labels, label_groups=LABEL_GROUPS)
    drr_n = NumpyDRR.from_volume(cta, det, labels=labels, label_groups=LABEL_GROUPS)
    assert drr_n.channel_names == drr_t.channel_names
    pose = N.pose_from_params(np.array([0.3, 0.1, -0.05]), np.array([4.0, 620.0, -6.0]))
    with torch.no_grad():
        want = drr_t(torch.as_tensor(pose, dtype=torch.float32)[None])[0].numpy()
    got = drr_n(pose)
    assert got.shape == want.shape == (3, 48, 40) and want[2].max() > 1.0
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * want.max())
    # Coarse render + bilinear resize == torch's interpolate(align_corners=False).
    coarse = det.resized(24, 20)
    with torch.no_grad():
        small = drr_t(torch.as_tensor(pose, dtype=torch.float32)[None], detector=coarse, channels=(0,))
        want_up = F.interpolate(small, size=det.shape, mode="bilinear", align_corners=False)[0].numpy()
    got_up = drr_n(pose, channels=(0,), render_px=24)
    np.testing.assert_allclose(got_up, want_up, rtol=1e-4, atol=1e-4 * want_up.max())
    np.testing.assert_allclose(resize_bilinear(got, det.shape), got, atol=1e-5)  # same size: unchanged


def test_numpy_similarity_and_normalisation_match_torch():
    a = RNG.random((2, 1, 40, 50))
    b = a + RNG.normal(scale=0.3, size=a.shape)
    want = mncc(torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32)).numpy()
    got = [numpy_similarity.mncc(a[i, 0], b[i, 0]) for i in range(2)]
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(normalize_minmax(a * 5 + 2), normalize_minmax(torch.as_tensor(a * 5 + 2)).numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="same shape"):
        numpy_similarity.mncc(a[0, 0], b[0, 0, :-1])


def test_numpy_decoding_matches_torch():
    raw, logits = RNG.normal(size=(6, 6)), RNG.normal(size=(6, 3))
    lateral = np.array([True, False, True, True, False, False])
    view = onnx_runtime.select_view(logits, lateral)
    np.testing.assert_array_equal(view, select_view(torch.as_tensor(logits), torch.as_tensor(lateral)).numpy())
    np.testing.assert_array_equal(onnx_runtime.select_view(logits, None), logits.argmax(1))
    np.testing.assert_allclose(
        onnx_runtime.decode_init_pose(raw, view), decode_init_pose(torch.as_tensor(raw), torch.as_tensor(view)).numpy(), atol=1e-9
    )
    np.testing.assert_allclose(onnx_runtime.residual_from_raw(raw), residual_from_raw(torch.as_tensor(raw)).numpy(), atol=1e-12)
    mirrored = RNG.normal(size=(6, 3))
    np.testing.assert_allclose(
        onnx_runtime.mirror_averaged_logits(logits, mirrored),
        mirror_averaged_logits(torch.as_tensor(logits), torch.as_tensor(mirrored)).numpy(), atol=1e-12,
    )


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
import numpy as np
from geopose.cta import load_cta
from geopose.dsa import read_dsa
from geopose.register import register_case_numpy
from geopose.register.record import build_record

folder = sys.argv[1]
cta = load_cta(f"{folder}/cta.nii.gz")
cranium = load_cta(f"{folder}/cranium.nii.gz", check_hu=False)
vessels = load_cta(f"{folder}/vessels.nii.gz", check_hu=False)
runs = {key: read_dsa(f"{folder}/dsa_{key}.dcm") for key in ("pa", "lat")}
seen = []
result = register_case_numpy(cta, runs, cranium_mask=cranium, segmentation=vessels, render_px=256,
                             progress=lambda stage, fraction, message: seen.append(stage))
record = build_record(result, runs)
json.dump({"record": record, "stages": seen, "torch_loaded": "torch" in sys.modules}, open(f"{folder}/numpy.json", "w"))
"""

_SLICER_RUN = """
import json, sys
import numpy as np
from geopose import mrml
from geopose.errors import InputError
from geopose.options import RegistrationOptions

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
out = logic.register(cta=cta, dsaPA=pa, dsaLAT=lat, options=RegistrationOptions(iterations=25, model_clip_percentiles=(2, 98)),
                     progress=lambda s, f, m: messages.append(m))
json.dump({
    "refused": refused,
    "messages": messages,
    "notes": out["record"]["notes"],
    "options": out["record"]["options"],
    "device": out["record"]["environment"]["device"],
    "torch_version": out["record"]["environment"]["torch"],
    "pose_ras": {k: mrml.transform_matrix(out[f"{k}Pose"]).tolist() for k in ("pa", "lat")},
    "record_pose_ras": {k: out["record"]["views"][k]["pose_ras"] for k in ("pa", "lat")},
    "table_rows": out["table"].GetTable().GetNumberOfRows(),
    "torch_loaded": "torch" in sys.modules,
}, open(f"{folder}/slicer.json", "w"))
"""


def _run_without_torch(script: str, *args: str) -> None:
    code = _BLOCK_TORCH + textwrap.dedent(script)
    env_path = [str(REPO / "Logic")]
    proc = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600,
        env={**__import__("os").environ, "PYTHONPATH": ":".join(env_path)},
    )
    assert proc.returncode == 0, proc.stderr[-4000:]


@pytest.fixture(scope="module")
def phantom_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("torch_free")
    case = phantom_case(5003, folder, spacing_mm=3.0)
    save_volume(case.cranium, folder / "cranium.nii.gz")
    save_volume(case.vessels, folder / "vessels.nii.gz")
    return folder


def test_registration_runs_without_torch_and_matches_the_torch_pipeline(phantom_folder):
    """Init + Refine in a process that cannot import torch: same poses as the torch
    pipeline (no TTO, models from the same shipped weights) to within float rounding."""
    if not (default_models_dir() / "geopose_init.onnx").is_file():
        pytest.skip("no shipped ONNX models")
    _run_without_torch(_LIBRARY_RUN, str(phantom_folder))
    out = json.loads((phantom_folder / "numpy.json").read_text())
    assert not out["torch_loaded"]
    assert {"prepare", "calibration", "init", "refine", "done"} <= set(out["stages"])
    record = out["record"]
    assert record["environment"]["torch"] == "not installed" and "tto_trace" not in record

    case = phantom_case(5003, phantom_folder, spacing_mm=3.0)
    init, refine = make_predictors(default_models_dir(), "torch")
    result = register_case(case.cta, case.runs, init=init, refine=refine, cranium_mask=case.cranium,
                           segmentation=case.vessels, options=RegistrationOptions(iterations=0, device="cpu"))
    for key in ("pa", "lat"):
        view = record["views"][key]
        want = result.views[key].final_pose[0].double().numpy()
        got = np.asarray(view["pose_centred"])
        assert view["view_label"] == result.views[key].init.view
        assert view["refinement"]["accepted"] == result.views[key].refine.accepted
        np.testing.assert_allclose(got[:3, 3], want[:3, 3], atol=0.5)  # mm
        angle = N.rotation_angle_rad(got[:3, :3].T @ want[:3, :3])
        assert np.degrees(angle) < 0.1
        assert view["final_mncc"] == pytest.approx(result.views[key].final_mncc, abs=0.01)
        assert view["silhouette_dice"] == pytest.approx(result.views[key].silhouette_dice, abs=0.01)


def test_slicer_logic_without_torch_runs_init_and_refine(phantom_folder):
    pytest.importorskip("slicer", reason="needs the slicer-core wheel (Slicer's MRML in Python)")
    if not (default_models_dir() / "geopose_init.onnx").is_file():
        pytest.skip("no shipped ONNX models")
    _run_without_torch(_SLICER_RUN, str(phantom_folder), str(REPO))
    out = json.loads((phantom_folder / "slicer.json").read_text())
    assert not out["torch_loaded"]
    assert "is not installed: install the PyTorch extension" in out["refused"] and "backend 'onnxruntime'" in out["refused"]
    assert any("test-time optimisation needs PyTorch" in m for m in out["messages"])
    assert out["notes"] and "skipped" in out["notes"][0]
    assert out["device"].startswith("cpu (numpy renderer, onnxruntime)") and out["torch_version"] == "not installed"
    for key in ("pa", "lat"):
        np.testing.assert_allclose(out["pose_ras"][key], out["record_pose_ras"][key], atol=1e-6)
    assert out["table_rows"] == 2
    assert out["options"]["model_clip_percentiles"] == [2.0, 98.0] and out["options"]["iterations"] == 0
