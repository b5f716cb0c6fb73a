"""GeoPoseLogic (GeoPoseModule/GeoPose.py) on real MRML (slicer-core) and Slicer's real Python
layer (``slicer_harness``: shared/slicer-api, newest release): result nodes, DSA nodes, import."""

from __future__ import annotations

import math
import os
from types import SimpleNamespace

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="needs the slicer-core wheel (Slicer's MRML in Python)")

import slicer_harness as H  # noqa: E402
from geopose import contract as C  # noqa: E402
from geopose import mrml  # noqa: E402
from geopose.dsa import DSARun  # noqa: E402
from geopose.errors import InputError  # noqa: E402
from geopose.options import RegistrationOptions, TTOSchedule  # noqa: E402
from geopose.geometry import CArmAngles, Detector, pose_from_carm_angles  # noqa: E402
from test_mrml_adapters import _cta, _pose  # noqa: E402

@pytest.fixture()
def module():
    """GeoPose.py on the newest Slicer Python layer, with a fresh ``slicer.mrmlScene``."""
    if not H.slicer_api().is_dir():
        pytest.skip(f"Slicer's Python layer not found at {H.slicer_api()}")
    mod = H.load_module(H.SLICER_TAGS[-1], mrml.new_scene())
    yield mod
    H.unload()


DET = Detector(40, 48, (0.8, 0.8), 1000.0)


def _run(primary: float) -> DSARun:
    rng = np.random.default_rng(int(abs(primary)))
    angles = CArmAngles(primary, 3.0, DET.sdd_mm, 700.0)
    return DSARun(rng.random((3, DET.rows, DET.cols), dtype=np.float32) * 100, DET, angles, 125.0)


def _result(poses: dict[str, np.ndarray]) -> SimpleNamespace:
    """A registration record with the fields GeoPoseLogic.addResultNodes reads."""
    views = {}
    for n, (key, pose) in enumerate(poses.items()):
        shifted = pose.copy()
        shifted[:3, 3] += [3.0, 4.0, 0.0]
        views[key] = SimpleNamespace(
            final_pose=pose, stage_poses={"init": shifted, "final": pose}, final_mncc=0.5 + 0.1 * n,
            silhouette_dice=0.9, quality=SimpleNamespace(flag="ok" if n else "doubtful", reasons=() if n else ("low mNCC",)),
            prepared=SimpleNamespace(map=np.full(DET.shape, 7.0 + n, np.float32)),
        )
    return SimpleNamespace(views=views, runtimes_s={"init": 0.02, "total": 1.5}, engine={"backend": "torch", "device": "cpu"},
                           registration=SimpleNamespace(mode="biplane-rigid", refine_start="rotation fused, isocentre PA",
                                                          chosen_start="Refine"))


def test_module_metadata(module):
    parent = SimpleNamespace(path=str(H.MODULE_FILE))
    module.GeoPose(parent)
    assert parent.title == "GeoPose" and parent.categories == ["Registration"]
    assert "van Herten" in parent.acknowledgementText and "projection-space calibration" in parent.acknowledgementText
    assert "5.8 or later" in parent.helpText and parent.contributors == list(module.CONTRIBUTORS)


def test_add_result_nodes_places_every_output(module):
    scene = slicer.mrmlScene
    cta, lab = _cta()
    cta_node = mrml.volume_to_node(scene, cta, "CTA")
    seg = mrml.segmentation_from_labelmap(scene, lab, {1: ("vessel", (1, 0, 0)), 2: ("blob", (0, 1, 0))}, "Vessels")
    before = (mrml.volume_from_node(cta_node).array.copy(), mrml.labelmap_from_segmentation(seg, cta_node)[0].array.copy())
    logic = module.GeoPoseLogic()
    labels, segments = logic.segmentationLabels(seg, cta_node)
    assert segments == {1: ("vessel", (1.0, 0.0, 0.0)), 2: ("blob", (0.0, 1.0, 0.0))}
    poses = {"pa": _pose(C.VIEW_PA), "lat": _pose(C.VIEW_LAT_PLUS)}
    runs = {"pa": _run(0.0), "lat": _run(-90.0)}
    out = logic.addResultNodes(cta, runs, _result(poses), labels, segments)
    for key, title in (("pa", "PA"), ("lat", "LAT")):
        pose_ras = cta.centred_to_ras @ poses[key]
        assert out[f"{key}Pose"].GetName() == f"GeoPose {title} pose"
        np.testing.assert_allclose(mrml.transform_matrix(out[f"{key}Pose"]), pose_ras, atol=1e-9)
        plane = mrml.detector_ijk_to_ras(DET, pose_ras)
        np.testing.assert_allclose(mrml.volume_from_node(out[f"{key}MAP"]).ijk_to_ras, plane, atol=1e-9)
        seq = out[f"{key}DSA"]
        np.testing.assert_array_equal(mrml.frames_from_sequence(seq), runs[key].frames)
        np.testing.assert_allclose(mrml.volume_from_node(seq.GetNthDataNode(2)).ijk_to_ras, plane, atol=1e-9)
        assert seq.GetNthIndexValue(1) == "0.125"  # 125 ms frame time, in s
        proj_seg = out[f"{key}Projection"].GetSegmentation()
        assert [proj_seg.GetSegment(s).GetName() for s in proj_seg.GetSegmentIDs()] == ["vessel", "blob"]
        proj, names = mrml.labelmap_from_segmentation(out[f"{key}Projection"], out[f"{key}MAP"], ["vessel"])
        want = mrml.project_labels(labels, [1], poses[key], DET)[0]
        assert want.sum() > 10
        np.testing.assert_array_equal(proj.array[0] == names["vessel"], want)
        np.testing.assert_allclose(out[f"{key}Camera"].GetPosition(), pose_ras[:3, 3], atol=1e-9)
    table = out["table"]
    cols = [table.GetColumnName(c) for c in range(table.GetNumberOfColumns())]
    assert cols[:4] == ["view", "mNCC", "silhouette Dice", "quality"]
    assert table.GetCellText(0, cols.index("quality")) == "doubtful"
    assert float(table.GetCellText(1, cols.index("mNCC"))) == pytest.approx(0.6)
    assert float(table.GetCellText(0, cols.index("init to final (mm)"))) == pytest.approx(5.0)
    assert float(table.GetCellText(0, cols.index("runtime total (s)"))) == 1.5
    assert table.GetCellText(0, cols.index("registration")) == "biplane-rigid"
    assert table.GetCellText(1, cols.index("Refine start")) == "rotation fused, isocentre PA"
    # The pixel axes of the registered pose and of the run's angles (PA at primary 0: L\F; LAT at -90: A\F).
    assert table.GetCellText(0, cols.index("pixel axes (DICOM angles)")) == "L\\F"
    assert table.GetCellText(1, cols.index("pixel axes (DICOM angles)")) == "A\\F"
    assert table.GetCellText(0, cols.index("pixel axes (registered)")) == "L\\F"
    assert logic.summary(out).splitlines() == ["PA: mNCC 0.500, doubtful", "LAT: mNCC 0.600, ok"]
    # Inputs unchanged.
    np.testing.assert_array_equal(mrml.volume_from_node(cta_node).array, before[0])
    np.testing.assert_array_equal(mrml.labelmap_from_segmentation(seg, cta_node)[0].array, before[1])


def test_dsa_run_from_node_uses_attributes_and_overrides(module):
    scene = slicer.mrmlScene
    logic = module.GeoPoseLogic()
    run = _run(-90.0)
    seq, _ = mrml.dsa_sequence_node(scene, run.frames, run.detector, np.eye(4), "in", 0.125, run.angles)
    back = logic.dsaRunFromNode(seq)
    np.testing.assert_array_equal(back.frames, run.frames)
    assert back.detector == run.detector and back.angles == run.angles and back.frame_time_ms == 125.0
    assert back.view_role == "LAT"
    over = logic.dsaRunFromNode(seq, {"primary_deg": 2.0, "sod_mm": 650.0})
    assert over.angles.primary_deg == 2.0 and over.angles.sod_mm == 650.0 and over.view_role == "PA"
    bare = scene.AddNewNodeByClass("vtkMRMLSequenceNode", "bare")
    for n in range(2):
        f = slicer.vtkMRMLScalarVolumeNode()
        f.SetAndObserveImageData(mrml.volumes.image_data_from_array(run.frames[n][None]))
        bare.SetDataNodeAtValue(f, str(n))
    with pytest.raises(InputError, match="missing in DSA node 'bare'"):
        logic.dsaRunFromNode(bare)
    geo = {"primary_deg": 0.0, "secondary_deg": 0.0, "sid_mm": 1000.0, "sod_mm": 650.0, "pixel_spacing_mm": (0.8, 0.8)}
    assert logic.dsaRunFromNode(bare, geo).detector == DET
    p = logic.getParameterNode()
    assert logic.overridesFromParameters(p, "pa") == {}
    p.overrideGeometry = True
    p.geometryLAT.primaryDeg, p.geometryLAT.sidMm, p.geometryLAT.pixelSpacingMm = -88.0, 1100.0, 0.3
    assert logic.overridesFromParameters(p, "lat") == {
        "primary_deg": -88.0, "secondary_deg": 0.0, "sid_mm": 1100.0, "pixel_spacing_mm": (0.3, 0.3)}


def test_register_without_torch_says_what_to_install(module, monkeypatch):
    scene = slicer.mrmlScene
    cta_node = mrml.volume_to_node(scene, _cta()[0], "CTA")
    logic = module.GeoPoseLogic()
    monkeypatch.setattr(logic, "torchAvailable", lambda: False)
    before = scene.GetNumberOfNodes()
    with pytest.raises(InputError, match="is not installed: install the PyTorch extension"):
        logic.register(cta=cta_node, dsaPA=cta_node, dsaLAT=cta_node, options=RegistrationOptions(backend="torch"))
    with pytest.raises(InputError, match="select a CTA volume and a PA and a lateral DSA run"):
        logic.register(cta=cta_node, dsaPA=None, dsaLAT=cta_node)
    assert scene.GetNumberOfNodes() == before  # nothing half-made


def test_import_dsa_places_run_on_nominal_plane(module, tmp_path):
    from geopose.dsa import write_dsa_nifti

    scene = slicer.mrmlScene
    cta, _ = _cta()
    cta_node = mrml.volume_to_node(scene, cta, "CTA")
    run = _run(-90.0)
    path = write_dsa_nifti(run, tmp_path / "lat.nii.gz")
    seq, browser = module.GeoPoseLogic().importDSA(str(path), "LAT", ctaNode=cta_node)
    np.testing.assert_allclose(mrml.frames_from_sequence(seq), run.frames, rtol=1e-5, atol=1e-3)
    nominal = cta.centred_to_ras @ pose_from_carm_angles(run.angles)
    np.testing.assert_allclose(mrml.volume_from_node(seq.GetNthDataNode(0)).ijk_to_ras,
                               mrml.detector_ijk_to_ras(run.detector, nominal), atol=1e-6)
    assert browser.GetProxyNode(seq) is not None


@pytest.mark.slow
def test_register_phantom_end_to_end(module, tmp_path):
    """The whole pipeline through GeoPoseLogic.register on a phantom case (needs the
    `geopose phantom` command and shipped models)."""
    from geopose.cli import main as geopose_main
    from geopose.phantom.labels import vessel_mask

    models = module.GeoPoseLogic.defaultModelsFolder()
    if not any(models.glob("*.pt")):
        pytest.skip(f"no GeoPose models in {models}")
    if geopose_main(["phantom", "--seed", "1", "--out", str(tmp_path)]) != 0:
        pytest.skip("`geopose phantom` is not available")
    scene = slicer.mrmlScene
    cta = mrml.read_volume_node(scene, tmp_path / "cta.nii.gz", "CTA")
    labels = mrml.volume_from_node(mrml.read_volume_node(scene, tmp_path / "labels.nii.gz", "labels", labelmap=True))
    seg = mrml.segmentation_from_labelmap(scene, labels.like(vessel_mask(labels.array).astype(np.uint8)), {1: ("vessels", (1, 0, 0))}, "V")
    logic = module.GeoPoseLogic()
    pa, _ = logic.importDSA(str(tmp_path / "dsa_pa.dcm"), "PA", ctaNode=cta)
    lat, _ = logic.importDSA(str(tmp_path / "dsa_lat.dcm"), "LAT", ctaNode=cta)
    before = mrml.volume_from_node(cta).array.copy()
    out = logic.register(cta=cta, dsaPA=pa, dsaLAT=lat, segmentation=seg, options=RegistrationOptions(device="cpu", tto=TTOSchedule(iterations=5)))
    ctaVol = mrml.volume_from_node(cta)
    np.testing.assert_array_equal(ctaVol.array, before)
    for key in ("pa", "lat"):
        want = ctaVol.centred_to_ras @ out["result"].views[key].final_pose
        np.testing.assert_allclose(mrml.transform_matrix(out[f"{key}Pose"]), want, atol=1e-6)
        # ... and equal the result record (result.json) of the same registration
        np.testing.assert_allclose(mrml.transform_matrix(out[f"{key}Pose"]), np.asarray(out["record"]["views"][key]["pose_ras"]), atol=1e-6)
    path = mrml.save_mrb(scene, tmp_path / "case.mrb")
    s2 = mrml.load_mrb(path)
    np.testing.assert_allclose(mrml.transform_matrix(s2.GetFirstNodeByName("GeoPose PA pose")),
                               mrml.transform_matrix(out["paPose"]), atol=1e-6)
    assert math.isfinite(float(out["result"].views["pa"].final_mncc))
    assert os.path.exists(path)
