"""The module (GeoPoseModule/GeoPose.py) on Slicer's real Python layer, 5.8.1 and 5.12.3.

``slicer_harness`` loads Slicer's unmodified ``ScriptedLoadableModule``, ``parameterNodeWrapper``,
``i18n`` and ``packaging`` from ``shared/slicer-api/<tag>`` over the ``slicer-core`` wheel's MRML,
with minimal ``qt``/``ctk`` stand-ins (``Testing/QtStandIns``). The panel is built from
``Resources/UI/GeoPose.ui`` with stand-in widgets keyed by objectName.

What these tests cannot cover without the Slicer application: rendering and layout of the
panel, Qt's own signal timing, the C++ behaviour of Slicer's widgets (a node combo box's
automatic selection and its "create new node" entry, the table view), file dialogs and
message boxes (answered by the test), the slice/3D views of "Show view", the Extensions
Manager, and real pip/PyTorch installations (the installers are recorded, not run).
"""

from __future__ import annotations

import ast
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="needs the slicer-core wheel (Slicer's MRML in Python)")

import slicer_harness as H  # noqa: E402
from geopose import limits, mrml  # noqa: E402
from geopose.errors import InputError  # noqa: E402
from geopose.geometry import CArmAngles, Detector  # noqa: E402
from geopose.options import RegistrationOptions  # noqa: E402

if not H.slicer_api().is_dir():
    pytest.skip(f"Slicer's Python layer not found at {H.slicer_api()}", allow_module_level=True)

DET = Detector(40, 48, (0.8, 0.8), 1000.0)
ANGLES = CArmAngles(-90.0, 3.0, 1000.0, 700.0)


@pytest.fixture(params=H.SLICER_TAGS)
def module(request):
    """GeoPose.py on one Slicer release's Python layer, with a fresh ``slicer.mrmlScene``."""
    mod = H.load_module(request.param, mrml.new_scene())
    yield mod
    H.unload()


def _ui_parameter_names() -> dict[str, str]:
    """``{SlicerParameterName: objectName}`` of the .ui file."""
    root = ET.parse(H.UI_FILE).getroot()
    names = {}
    for widget in root.iter("widget"):
        for prop in widget.findall("property"):
            if prop.get("name") == "SlicerParameterName":
                names[prop.findtext("string")] = widget.get("name")
    return names


def _parameter_names(module) -> list[str]:
    from slicer.parameterNodeWrapper import nestedParameterNames

    return nestedParameterNames(module.GeoPoseParameterNode)


def _annotation(p, name, cls):
    from slicer.parameterNodeWrapper import findFirstAnnotation, splitAnnotations

    return findFirstAnnotation(splitAnnotations(p.dataType(name))[1], cls)


def _output_nodes(scene) -> dict:
    """One real node per output parameter (and per node-type input), with content, so a scene bundle holds them."""
    from test_mrml_adapters import _cta

    cta, labels = _cta()
    cta_node = mrml.volume_to_node(scene, cta, "CTA")  # the first volume: the panel pre-selects it
    pose = np.eye(4)
    pose[:3, 3] = (0, -650, 0)
    frames = np.random.default_rng(0).random((2, DET.rows, DET.cols), dtype=np.float32)
    seq, _ = mrml.dsa_sequence_node(scene, frames, DET, pose, "DSA run", 0.1, ANGLES)
    mask = {"v": (np.ones((1, DET.rows, DET.cols), np.uint8), (1.0, 0.0, 0.0))}
    return {
        "cta": cta_node,
        "craniumMask": mrml.segmentation_from_labelmap(scene, labels, {1: ("skull", (1, 1, 1))}, "Cranium"),
        "segmentation": mrml.segmentation_from_labelmap(scene, labels, {1: ("vessel", (1, 0, 0))}, "Vessels"),
        "dsaPA": seq,
        "dsaLAT": mrml.plane_volume_node(scene, frames[0], DET, pose, "LAT frames"),
        "pose": mrml.pose_transform_node(scene, pose, "pose"),
        "camera": mrml.camera_node(scene, pose, DET, "camera"),
        "frustum": mrml.frustum_model_node(scene, pose, DET, "frustum"),
        "dsa": mrml.dsa_sequence_node(scene, frames, DET, pose, "out DSA", 0.1, ANGLES)[0],
        "map": mrml.plane_volume_node(scene, frames[0], DET, pose, "map"),
        "projection": mrml.segmentation_from_masks(scene, mask, mrml.detector_ijk_to_ras(DET, pose), "projection"),
        "resultsTable": mrml.result_table_node(scene, [{"view": "PA", "mNCC": 0.5}], "table"),
    }


def _values(p, names) -> dict:
    """Every parameter's value, nodes by name (comparable across scenes)."""
    return {n: (v.GetName() if hasattr(v, "GetName") else v) for n in names for v in [p.getValue(n)]}


# ------------------------------------------------------------------ parameter node
def test_parameter_node_constructs_with_the_library_defaults(module):
    p = module.GeoPoseLogic().getParameterNode()
    assert p.dsaPA is None and p.dsaLAT is None and p.cta is None
    defaults = RegistrationOptions()
    assert (p.backend, p.device, p.refineSteps, p.iterations) == (
        defaults.backend, defaults.device, defaults.refine_steps, defaults.iterations)
    assert module.GeoPoseLogic.optionsFromParameters(p) == defaults
    assert (_annotation(p, "refineSteps", module.WithinRange).minimum, _annotation(p, "refineSteps", module.WithinRange).maximum) == limits.REFINE_STEPS
    assert (_annotation(p, "iterations", module.WithinRange).minimum, _annotation(p, "iterations", module.WithinRange).maximum) == limits.ITERATIONS


def test_every_parameter_round_trips_through_the_node_and_a_saved_scene(module, tmp_path):
    scene = slicer.mrmlScene
    p = module.GeoPoseLogic().getParameterNode()
    names = _parameter_names(module)
    nodes = _output_nodes(scene)
    defaults = _values(p, names)
    changed = {}
    for name in names:
        field = name.split(".")[-1]
        default = p.getValue(name)
        if field in nodes:
            value = nodes[field]
        elif isinstance(default, bool):
            value = not default
        elif isinstance(default, (int, float)):
            bound = _annotation(p, name, module.WithinRange)
            value = type(default)(bound.maximum if default != bound.maximum else bound.minimum)
        else:
            value = next(c for c in _annotation(p, name, module.Choice).choices if c != default)
        p.setValue(name, value)
        changed[name] = value
    want = _values(p, names)
    assert all(want[n] != defaults[n] for n in names)
    assert want == {n: (v.GetName() if hasattr(v, "GetName") else v) for n, v in changed.items()}
    # A second wrapper on the same MRML node reads the same values ...
    assert _values(module.GeoPoseParameterNode(p.parameterNode), names) == want
    # ... and so does one on the node of the saved and reloaded scene.
    reloaded = mrml.load_mrb(mrml.save_mrb(scene, tmp_path / "scene.mrb"))
    node = reloaded.GetFirstNodeByClass("vtkMRMLScriptedModuleNode")
    assert _values(module.GeoPoseParameterNode(node), names) == want


def test_validators_reject_out_of_range_values(module):
    p = module.GeoPoseLogic().getParameterNode()
    checked = 0
    for name in _parameter_names(module):
        bound = _annotation(p, name, module.WithinRange)
        if bound is not None:
            before = p.getValue(name)
            for bad in (bound.maximum + 1, bound.minimum - 1):
                with pytest.raises(ValueError, match="within range"):
                    p.setValue(name, type(before)(bad))
            assert p.getValue(name) == before
            checked += 1
    assert checked == 12  # refineSteps, iterations and 2 x 5 geometry fields
    for name in ("backend", "device"):
        with pytest.raises(ValueError, match="must be in one of"):
            p.setValue(name, "tpu")


def test_connect_gui_maps_every_ui_name_to_a_parameter_and_back(module):
    ui_names = _ui_parameter_names()
    assert set(ui_names) == set(_parameter_names(module))
    p = module.GeoPoseLogic().getParameterNode()
    ui = slicer.util.childWidgetVariables(H.load_ui())
    p.connectGui(ui)
    (mapping,) = p._parameterGUIs.values()
    assert set(mapping) == set(ui_names)
    for name, connector in mapping.items():
        assert connector.widget() is getattr(ui, ui_names[name])


def test_every_ui_name_the_module_uses_exists_in_the_ui_file():
    tree = ast.parse(H.MODULE_FILE.read_text())
    used = {n.attr for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Attribute) and n.value.attr == "ui"}
    defined = {w.get("name") for w in ET.parse(H.UI_FILE).getroot().iter("widget")}
    assert used and used <= defined, sorted(used - defined)


def test_optional_and_dsa_selectors_do_not_preselect_a_node():
    """A combo with noneEnabled false selects the first node it accepts (a DSA combo would take the CTA):
    only the CTA may be pre-selected."""
    root = ET.parse(H.UI_FILE).getroot()
    combos = {w.get("name"): {p.get("name"): p for p in w.findall("property")}
              for w in root.iter("widget") if w.get("class") == "qMRMLNodeComboBox"}
    for name, props in combos.items():
        none_enabled = props["noneEnabled"].findtext("bool") == "true"
        assert none_enabled == (name != "ctaSelector"), name


def test_the_module_file_runs_on_python_3_9():
    """Slicer 5.8 runs Python 3.9: no ``X | Y`` annotation (evaluated at import) and no 3.10 syntax."""
    tree = ast.parse(H.MODULE_FILE.read_text(), feature_version=(3, 9))
    annotations = [n.annotation for n in ast.walk(tree) if isinstance(n, (ast.arg, ast.AnnAssign)) and n.annotation]
    annotations += [n.returns for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.returns]
    assert not [ast.unparse(a) for a in annotations if any(isinstance(b, ast.BinOp) for b in ast.walk(a))]


# ------------------------------------------------------------------ the panel
def test_widget_setup_runs_on_the_ui_and_follows_the_parameter_node(module):
    scene = slicer.mrmlScene
    nodes = _output_nodes(scene)
    w = H.new_widget(module)
    p = w._parameterNode
    assert p.cta is nodes["cta"] and w.ui.ctaSelector.currentNode() is nodes["cta"]
    assert w.ui.dsaPASelector.currentNode() is None and not w.ui.applyButton.enabled
    assert not w.ui.progressBar.visible and not w.ui.cancelButton.enabled and not w.ui.showPAButton.enabled
    p.dsaPA, p.dsaLAT = nodes["dsaPA"], nodes["dsaLAT"]
    assert w.ui.dsaLATSelector.currentNode() is nodes["dsaLAT"] and w.ui.applyButton.enabled
    w.ui.iterationsSpinBox.value = 7  # GUI -> parameter node
    w.ui.geometryCollapsibleButton  # (exists; collapsed state is Qt's)
    w.ui.sodMmPASpinBox.value = 640.0
    w.ui.backendComboBox.currentIndex = w.ui.backendComboBox._items.index("onnxruntime")
    assert (p.iterations, p.geometryPA.sodMm, p.backend) == (7, 640.0, "onnxruntime")
    p.refineSteps = 3  # parameter node -> GUI
    assert w.ui.refineStepsSpinBox.value == 3
    assert (w.ui.refineStepsSpinBox.minimum, w.ui.refineStepsSpinBox.maximum) == limits.REFINE_STEPS
    # Leaving and re-entering the module keeps one connection per widget (Slicer 5.8's connectGui returns no tag).
    for _ in range(2):
        w.exit()
        w.enter()
    assert len(w.ui.iterationsSpinBox.valueChanged._slots) == 1
    w.ui.iterationsSpinBox.value = 9
    assert p.iterations == 9


def test_an_older_slicer_is_refused_with_the_minimum_version(module):
    slicer.app.minorVersion = 6
    w = H.new_widget(module)
    (label,) = [c for c in w.parent.children() if isinstance(c, sys.modules["qt"].QLabel)]
    assert label.text == module.MINIMUM_SLICER_TEXT and "5.8 or later" in label.text
    with pytest.raises(InputError, match="needs 3D Slicer 5.8 or later"):
        module.GeoPoseLogic().register(cta=None, dsaPA=None, dsaLAT=None)


# ------------------------------------------------------------------ dependencies
@pytest.fixture()
def installs(monkeypatch):
    """Records what would be installed (``slicer.util`` install and dialog calls; a PyTorchUtils stand-in)."""
    calls = {"pip": [], "torch": [], "asked": []}
    # Slicer 5.12's packaging calls slicer.util.executePythonModule, which the slicer-core 5.11 wheel's util lacks
    monkeypatch.setattr(slicer.util, "executePythonModule", lambda module, args, **kw: calls["pip"].append(args), raising=False)
    monkeypatch.setattr(slicer.util, "pip_install", lambda reqs, **kw: calls["pip"].append(list(reqs)))
    answer = {"ok": True}

    def confirm(text, *args, **kwargs):
        calls["asked"].append(text)
        return answer["ok"]

    monkeypatch.setattr(slicer.util, "confirmOkCancelDisplay", confirm)

    class PyTorchUtilsLogic:
        def installTorch(self, askConfirmation=False, torchVersionRequirement=None, **kwargs):
            calls["torch"].append({"askConfirmation": askConfirmation, "torchVersionRequirement": torchVersionRequirement})
            return None if not answer["ok"] else types.ModuleType("torch")

    monkeypatch.setitem(sys.modules, "PyTorchUtils", types.SimpleNamespace(PyTorchUtilsLogic=PyTorchUtilsLogic))
    calls["answer"] = answer
    return calls


def test_version_floors_are_enforced_and_a_decline_returns_false(module, monkeypatch, installs):
    logic = module.GeoPoseLogic()
    assert logic.missingRequirements() == []  # this environment meets every floor
    monkeypatch.setattr(module, "REQUIREMENTS", module.REQUIREMENTS + ("numpy>=999",))
    assert logic.missingRequirements() == ["numpy>=999"]  # installed, but older than the floor
    installs["answer"]["ok"] = False
    assert logic.ensureDependencies(askUser=True) is False
    assert installs["asked"] and installs["pip"] == []
    installs["answer"]["ok"] = True
    with pytest.raises(InputError, match="could not be installed: numpy>=999"):
        logic.ensureDependencies(askUser=True)
    (args,) = installs["pip"]
    assert "numpy>=999" in args
    new_slicer = slicer.app.minorVersion >= 12
    assert ("install" in args) == new_slicer  # 5.12+: slicer.packaging.pip_ensure -> pip install; older: util.pip_install
    assert installs["torch"] == []


def test_torch_is_installed_only_when_asked_for_through_pytorch_utils(module, monkeypatch, installs, tmp_path):
    from geopose.dsa import DSARun, write_dsa_nifti

    logic = module.GeoPoseLogic()
    monkeypatch.setattr(module, "TORCH_REQUIREMENT", ">=999")  # torch here is older than that
    assert not logic.torchAvailable()
    assert logic.ensureDependencies(askUser=True) is True and installs["torch"] == []
    installs["answer"]["ok"] = False
    assert logic.ensureDependencies(askUser=True, torch=True) is False
    assert installs["torch"] == [{"askConfirmation": True, "torchVersionRequirement": ">=999"}]
    monkeypatch.setattr(module, "TORCH_MINIMUM_PYTHON", (99, 0))
    with pytest.raises(InputError, match="needs Slicer 5.10 or later"):
        logic.ensureDependencies(torch=True)
    # Importing a DSA run from the panel never asks for PyTorch.
    installs["torch"].clear()
    run = DSARun(np.ones((2, DET.rows, DET.cols), np.float32), DET, ANGLES, 100.0)
    monkeypatch.setattr(sys.modules["qt"].QFileDialog, "answer", str(write_dsa_nifti(run, tmp_path / "pa.nii.gz")))
    w = H.new_widget(module)
    w.ui.importPAButton.click()
    assert w._parameterNode.dsaPA is not None and w._parameterNode.dsaPA.GetNumberOfDataNodes() == 2
    assert installs["torch"] == []


# ------------------------------------------------------------------ inputs and errors
def test_dsa_node_goes_through_the_readers_checks(module):
    scene = slicer.mrmlScene
    frames = np.ones((2, DET.rows, DET.cols), np.float32)
    seq, _ = mrml.dsa_sequence_node(scene, frames, DET, np.eye(4), "run", 0.1, ANGLES)
    logic = module.GeoPoseLogic()
    run = logic.dsaRunFromNode(seq)
    assert run.detector == DET and run.angles == ANGLES and run.frame_time_ms == pytest.approx(100.0)
    assert run.metadata["geometry_sources"]["sod_mm"] == "Slicer node run"
    with pytest.raises(ValueError, match="not shorter than the source-to-detector"):
        logic.dsaRunFromNode(seq, {"sod_mm": 1200.0})
    bare = mrml.plane_volume_node(scene, frames[0], DET, np.eye(4), "bare")  # no geometry attributes
    with pytest.raises(ValueError, match="missing in DSA node 'bare'"):
        logic.dsaRunFromNode(bare)


def test_a_user_error_on_apply_is_shown_as_one_line(module, monkeypatch):
    scene = slicer.mrmlScene
    nodes = _output_nodes(scene)
    shown = []
    monkeypatch.setattr(slicer.util, "errorDisplay", lambda text, **kw: shown.append((text, kw)))
    w = H.new_widget(module)
    p = w._parameterNode
    p.dsaPA, p.dsaLAT = nodes["dsaPA"], nodes["dsaLAT"]
    p.outputsPA.map = nodes["cta"]  # an input chosen as an output
    before = scene.GetNumberOfNodes()
    w.ui.applyButton.click()  # no exception escapes the panel
    ((text, kwargs),) = shown
    assert text == "output paMAP is the input node 'CTA': choose another output node, inputs are never overwritten"
    assert "\n" not in text and "detailedText" not in kwargs and w.ui.statusLabel.text == text
    assert scene.GetNumberOfNodes() == before and w.ui.applyButton.enabled and not w.ui.progressBar.visible


# ------------------------------------------------------------------ Apply: outputs are references
@pytest.fixture(scope="module")
def phantom(tmp_path_factory) -> Path:
    from geopose.phantom.cli import write_phantom

    folder = tmp_path_factory.mktemp("slicer_phantom")
    write_phantom(5003, folder, spacing_mm=4.0, max_matrix_px=128)  # small: seconds per registration
    return folder


@pytest.fixture()
def newest():
    """GeoPose.py on the newest Slicer layer only: for the tests that register (seconds each); the
    parameter packs and node references of both layers are covered by the round-trip test above."""
    mod = H.load_module(H.SLICER_TAGS[-1], mrml.new_scene())
    yield mod
    H.unload()


def test_apply_again_updates_the_same_nodes_and_the_references_survive_a_saved_scene(newest, phantom, tmp_path):
    module = newest
    scene = slicer.mrmlScene
    logic = module.GeoPoseLogic()
    cta = mrml.read_volume_node(scene, phantom / "cta.nii.gz", "CTA")
    w = H.new_widget(module)
    p = w._parameterNode
    p.dsaPA = logic.importDSA(str(phantom / "dsa_pa.dcm"), "PA", ctaNode=cta)[0]
    p.dsaLAT = logic.importDSA(str(phantom / "dsa_lat.dcm"), "LAT", ctaNode=cta)[0]
    p.iterations, p.refineSteps = 0, 1  # the shortest registration; TTO is covered by the library's tests
    chosen = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "my PA pose")
    p.outputsPA.pose = chosen  # an output the user chose: used, not replaced
    w.ui.applyButton.click()
    counts = [scene.GetNumberOfNodes()]
    first = logic.outputNodes(p)
    assert len(first) == 11 and first["paPose"] is chosen and chosen.GetName() == "my PA pose"  # 5 per view (no segmentation) + table
    pose_first = mrml.transform_matrix(chosen)
    assert not np.allclose(pose_first, np.eye(4))
    assert w.ui.resultsTableView.mrmlTableNode() is p.resultsTable and "PA: mNCC" in w.ui.statusLabel.text
    assert w.ui.showPAButton.enabled and w.ui.showLATButton.enabled
    p.refineSteps = 0
    w.ui.applyButton.click()
    counts.append(scene.GetNumberOfNodes())
    assert counts[1] == counts[0]
    assert logic.outputNodes(p) == first  # the same nodes, updated
    assert p.resultsTable.GetTable().GetNumberOfRows() == 2
    seq = p.outputsLAT.dsa
    assert seq.GetNumberOfDataNodes() == mrml.frames_from_node(p.dsaLAT).shape[0]
    # The references survive a saved and reloaded scene.
    reloaded = mrml.load_mrb(mrml.save_mrb(scene, tmp_path / "case.mrb"))
    again = module.GeoPoseParameterNode(reloaded.GetFirstNodeByClass("vtkMRMLScriptedModuleNode"))
    back = logic.outputNodes(again)
    assert {k: n.GetName() for k, n in back.items()} == {k: n.GetName() for k, n in first.items()}
    assert all(back[k].GetScene() is reloaded for k in back)
    np.testing.assert_allclose(mrml.transform_matrix(back["paPose"]), mrml.transform_matrix(chosen), atol=1e-9)
    np.testing.assert_array_equal(mrml.volume_from_node(back["latMAP"]).array, mrml.volume_from_node(first["latMAP"]).array)
    assert again.dsaPA.GetName() == p.dsaPA.GetName() and again.cta.GetName() == "CTA"


@pytest.mark.slow
def test_the_self_test_passes_on_the_phantom(module):
    """GeoPoseTest as Slicer's Reload-and-Test runs it: full registration on CPU (about 2 minutes)."""
    module.GeoPoseTest().runTest()
