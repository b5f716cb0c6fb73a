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
from geopose.errors import InputError  # noqa: E402
from geopose.options import RefineOptions, RegistrationOptions, SearchOptions, TTOSchedule, setting_paths  # noqa: E402
from geopose.geometry import pose_from_carm_angles  # noqa: E402
from test_mrml_adapters import _cta, _pose, _result, _run  # noqa: E402

@pytest.fixture()
def module():
    """GeoPose.py on the newest Slicer Python layer, with a fresh ``slicer.mrmlScene``."""
    if not H.slicer_api().is_dir():
        pytest.skip(f"Slicer's Python layer not found at {H.slicer_api()}")
    mod = H.load_module(H.SLICER_TAGS[-1], mrml.new_scene())
    yield mod
    H.unload()


def test_module_metadata(module):
    parent = SimpleNamespace(path=str(H.MODULE_FILE))
    module.GeoPose(parent)
    assert parent.title == "GeoPose" and parent.categories == ["Registration"]
    assert "van Herten" in parent.acknowledgementText and "projection-space calibration" in parent.acknowledgementText
    assert "5.8 or later" in parent.helpText and parent.contributors == list(module.CONTRIBUTORS)


def test_summary_and_parameters_map_to_the_library(module):
    """The logic's parameter-node mappings: options (every RegistrationOptions field the panel holds),
    geometry overrides (geopose.mrml.geometry_overrides) and the summary of a results table."""
    scene = slicer.mrmlScene
    logic = module.GeoPoseLogic()
    p = logic.getParameterNode()
    assert logic.overridesFromParameters(p, "pa") == {}
    p.overrideGeometry = True
    p.geometryLAT.primaryDeg, p.geometryLAT.sidMm, p.geometryLAT.pixelSpacingMm = -88.0, 1100.0, 0.3
    assert logic.overridesFromParameters(p, "lat") == {
        "primary_deg": -88.0, "secondary_deg": 0.0, "sid_mm": 1100.0, "pixel_spacing_mm": (0.3, 0.3)}
    assert logic.overridesFromParameters(p, "pa") == {"primary_deg": 0.0, "secondary_deg": 0.0}
    p.backend, p.refineSteps, p.iterations, p.similaritySearch, p.independentViews = "onnxruntime", 2, 7, False, True
    assert logic.optionsFromParameters(p) == RegistrationOptions(
        backend="onnxruntime", independent_views=True, refine=RefineOptions(steps=2), tto=TTOSchedule(iterations=7),
        search=SearchOptions(enabled=False))
    assert set(module.OPTION_FIELDS.values()) <= {path for path, _ in setting_paths()}
    cta = _cta()[0]
    out = mrml.result_nodes(scene, mrml.RegistrationInputs(cta, {"pa": _run(0.0), "lat": _run(-90.0)}),
                            _result({"pa": _pose(C.VIEW_PA), "lat": _pose(C.VIEW_LAT_PLUS)}))
    assert logic.summary(out).splitlines() == ["PA: mNCC 0.500, doubtful", "LAT: mNCC 0.600, ok"]
    assert logic.summary({}) == ""


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
