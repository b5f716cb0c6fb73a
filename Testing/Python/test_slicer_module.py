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
import importlib
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
        defaults.backend, defaults.device, defaults.refine.steps, defaults.tto.iterations)
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
    """Records what would be installed: Slicer 5.8's ``slicer.util.pip_install`` and 5.12's
    ``slicer.packaging.pip_install`` (with the constraints file's text at the time of the call),
    the dialogs (answered by ``answer``), a PyTorchUtils stand-in; ``fail`` makes pip fail."""
    import subprocess

    calls = {"pip": [], "constraints": [], "torch": [], "asked": [], "plans": []}
    answer = {"ok": True}
    fail = {"pip": False}

    def record(args, constraints=None):
        calls["pip"].append(list(args))
        if constraints is not None:
            calls["constraints"].append(Path(constraints).read_text())
        if fail["pip"]:
            raise subprocess.CalledProcessError(1, ["PythonSlicer", "-m", "pip", "install", *args])

    def pip_install_58(args, **kw):  # Slicer 5.8: slicer.util.pip_install(["-c", file, *requirements])
        args = list(args)
        record(args, args[args.index("-c") + 1] if "-c" in args else None)

    monkeypatch.setattr(slicer.util, "pip_install", pip_install_58)
    # Slicer 5.12's packaging calls slicer.util.executePythonModule, which the slicer-core 5.11 wheel's util lacks
    monkeypatch.setattr(slicer.util, "executePythonModule", lambda module, args, **kw: record(args), raising=False)
    try:  # Slicer 5.12: pip_ensure -> packaging.pip_install(requirements, constraints=...)
        packaging = importlib.import_module("slicer.packaging")
    except ImportError:
        pass
    else:
        monkeypatch.setattr(packaging, "pip_install", lambda reqs, constraints=None, **kw: record(reqs, constraints))

    def confirm(text, *args, **kwargs):
        calls["asked"].append(text)
        return answer["ok"]

    monkeypatch.setattr(slicer.util, "confirmOkCancelDisplay", confirm)

    class PyTorchUtilsLogic:
        def installTorch(self, askConfirmation=False, torchVersionRequirement=None, **kwargs):
            calls["torch"].append({"askConfirmation": askConfirmation, "torchVersionRequirement": torchVersionRequirement})
            return None if not answer["ok"] else types.ModuleType("torch")

    monkeypatch.setitem(sys.modules, "PyTorchUtils", types.SimpleNamespace(PyTorchUtilsLogic=PyTorchUtilsLogic))
    calls["answer"], calls["fail"] = answer, fail
    return calls


@pytest.fixture()
def absent(module, monkeypatch, installs):
    """A requirement that is not installed ("geopose-absent-probe>=1.0"), in a Slicer out of testing
    mode, with pip's dry run answered (its real run in Slicer 5.8's environment: test_python39.py)."""
    requirement = "geopose-absent-probe>=1.0"
    monkeypatch.setattr(module.dependencies, "SLICER_REQUIREMENTS", module.dependencies.SLICER_REQUIREMENTS + (requirement,))
    slicer.app.testing = False

    def plan(python, requirements, constraints):
        installs["plans"].append((python, list(requirements), Path(constraints).read_text()))
        return [("geopose-absent-probe", "1.2"), ("its-dependency", "0.3")]

    monkeypatch.setattr(module.dependencies, "plan_install", plan)
    return requirement


def test_a_first_install_pins_every_installed_package_and_shows_the_versions(module, installs, absent):
    from importlib.metadata import version

    logic = module.GeoPoseLogic()
    assert module.dependencies.missing() == [absent]  # this environment meets every other floor
    installs["answer"]["ok"] = False
    assert logic.ensureDependencies(askUser=True) is False  # declined: nothing installed
    assert installs["pip"] == [] and len(installs["asked"]) == 1
    assert "geopose-absent-probe 1.2\nits-dependency 0.3" in installs["asked"][0]
    assert "none of which is changed" in installs["asked"][0]
    installs["answer"]["ok"] = True
    with pytest.raises(InputError, match="could not be installed: geopose-absent-probe>=1.0"):  # the recorder installs nothing
        logic.ensureDependencies(askUser=True)
    ((args,),) = [installs["pip"]]
    assert absent in args and ("-c" in args) == (slicer.app.minorVersion < 12)
    # pip ran (and planned) with every package of this Python pinned at its version: numpy stays.
    (constraints,) = installs["constraints"]
    assert f"numpy=={version('numpy')}\n" in constraints and f"pydicom=={version('pydicom')}\n" in constraints
    assert all(plan[2] == constraints for plan in installs["plans"])
    assert installs["torch"] == []


def test_a_requirement_above_a_package_slicer_ships_is_refused_before_pip(module, monkeypatch, installs):
    slicer.app.testing = False
    monkeypatch.setattr(module.dependencies, "SLICER_REQUIREMENTS", module.dependencies.SLICER_REQUIREMENTS + ("numpy>=999",))
    with pytest.raises(InputError, match=r"GeoPose needs numpy>=999 \(this Slicer has .*never replaces a package of Slicer"):
        module.GeoPoseLogic().ensureDependencies(askUser=True)
    assert installs["pip"] == [] and installs["asked"] == []


def test_nothing_is_installed_in_testing_mode(module, installs, absent):
    slicer.app.testing = True
    with pytest.raises(InputError, match="testing mode"):
        module.GeoPoseLogic().ensureDependencies(askUser=True)
    assert installs["pip"] == [] and installs["asked"] == [] and installs["plans"] == []


def test_a_failed_pip_install_is_one_line(module, monkeypatch, installs, absent):
    installs["fail"]["pip"] = True
    shown = []
    monkeypatch.setattr(slicer.util, "errorDisplay", lambda text, **kw: shown.append((text, kw)))
    with pytest.raises(InputError, match=r"pip could not install geopose-absent-probe>=1.0 \(exit code 1"):
        module.GeoPoseLogic().ensureDependencies(askUser=True)
    # From the panel: one dialog with that line, no traceback.
    w = H.new_widget(module)
    _output_nodes(slicer.mrmlScene)
    w._parameterNode.dsaPA = w._parameterNode.dsaLAT = slicer.mrmlScene.GetFirstNodeByName("DSA run")
    w.ui.applyButton.click()
    ((text, kwargs),) = shown
    assert text.startswith("pip could not install") and "\n" not in text and "detailedText" not in kwargs


def test_torch_is_installed_only_when_asked_for_through_pytorch_utils(module, monkeypatch, installs, tmp_path):
    from geopose.dsa import DSARun, write_dsa_nifti

    logic = module.GeoPoseLogic()
    monkeypatch.setattr(module.dependencies, "TORCH_REQUIREMENT", ">=999")  # torch here is older than that
    assert not logic.torchAvailable()
    assert logic.ensureDependencies(askUser=True) is True and installs["torch"] == []
    installs["answer"]["ok"] = False
    assert logic.ensureDependencies(askUser=True, torch=True) is False
    assert installs["torch"] == [{"askConfirmation": True, "torchVersionRequirement": ">=999"}]
    monkeypatch.setattr(module.dependencies, "TORCH_MINIMUM_PYTHON", (99, 0))
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


def _panel_on_phantom(module, phantom, iterations=0, refineSteps=1):
    """The panel with the phantom's CTA and DSA runs chosen (the shortest registration by default)."""
    scene = slicer.mrmlScene
    logic = module.GeoPoseLogic()
    cta = mrml.read_volume_node(scene, phantom / "cta.nii.gz", "CTA")
    w = H.new_widget(module)
    p = w._parameterNode
    p.cta = cta
    p.dsaPA = logic.importDSA(str(phantom / "dsa_pa.dcm"), "PA", ctaNode=cta)[0]
    p.dsaLAT = logic.importDSA(str(phantom / "dsa_lat.dcm"), "LAT", ctaNode=cta)[0]
    p.iterations, p.refineSteps, p.backend = iterations, refineSteps, "onnxruntime"
    return w


def _count_registrations(module, monkeypatch) -> list:
    """The library's ``register_case`` as the module calls it, counted (it runs unchanged)."""
    from geopose.register import pipeline

    calls = []
    real = pipeline.register_case

    def counted(*args, **kwargs):
        calls.append(kwargs.get("options"))
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "register_case", counted)
    return calls


def test_apply_cannot_start_again_while_a_registration_runs(newest, phantom, monkeypatch):
    """A user edits a spin box and clicks Apply again while the registration runs (events processed
    during the run): the panel is locked, the click does nothing, one registration runs and the
    panel is unlocked after it."""
    module = newest
    app = slicer.app
    runs = _count_registrations(module, monkeypatch)
    w = _panel_on_phantom(module, phantom)
    seen = {}

    def user_during_run():
        seen["locked"] = {name: getattr(w.ui, name).isEnabled() for name in ("iterationsSpinBox", "ctaSelector", "applyButton",
                                                                            "importPAButton", "cancelButton")}
        if w.ui.iterationsSpinBox.isEnabled():  # a user can only edit what is enabled
            w.ui.iterationsSpinBox.value = 1
        w._parameterNode.refineSteps = 2  # e.g. from the Python console: Apply stays disabled
        seen["apply after edit"] = w.ui.applyButton.enabled
        w.ui.applyButton.click()
        w.onApplyButton()  # a click queued before Apply was disabled re-enters the slot

    app.post(user_during_run)
    w.ui.applyButton.click()
    assert len(runs) == 1
    assert seen["locked"] == {"iterationsSpinBox": False, "ctaSelector": False, "applyButton": False,
                              "importPAButton": False, "cancelButton": True}
    assert seen["apply after edit"] is False
    assert "PA: mNCC" in w.ui.statusLabel.text and w._parameterNode.outputsPA.pose is not None
    assert w.ui.applyButton.enabled and not w.ui.cancelButton.enabled and not w.ui.progressBar.visible
    assert w.ui.iterationsSpinBox.isEnabled() and w.ui.importPAButton.isEnabled()


def test_cancel_stops_the_run_without_an_error_and_changes_no_output(newest, phantom, monkeypatch):
    module = newest
    shown = []
    monkeypatch.setattr(slicer.util, "errorDisplay", lambda text, **kw: shown.append(text))
    w = _panel_on_phantom(module, phantom)
    scene = slicer.mrmlScene
    before = scene.GetNumberOfNodes()
    slicer.app.post(w.ui.cancelButton.click)
    w.ui.applyButton.click()
    assert shown == []  # no "Registration failed." dialog, no traceback
    assert w.ui.statusLabel.text == "Cancelled: no output node was changed."
    assert scene.GetNumberOfNodes() == before and module.GeoPoseLogic.outputNodes(w._parameterNode) == {}
    assert w.ui.applyButton.enabled and not w.ui.cancelButton.enabled and not w.ui.progressBar.visible
    # The next Apply runs to its end.
    w.ui.applyButton.click()
    assert "PA: mNCC" in w.ui.statusLabel.text and shown == []


def test_the_networks_estimate_is_shown_while_the_tto_runs_and_the_result_moves_the_same_nodes(newest, phantom):
    """Apply with the TTO: the output nodes show the networks' estimate (pose transforms marked preliminary, the
    status saying so) while the registration goes on; the end moves those nodes, marked final, to the result
    (here the estimate again: the trust rule keeps it on this coarse 4 mm phantom)."""
    w = _panel_on_phantom(newest, phantom, iterations=3)
    w._parameterNode.backend = "torch"
    scene, seen = slicer.mrmlScene, []
    shown = w._shown

    def record(preliminary, outputs):
        shown(preliminary, outputs)
        seen.append((preliminary, dict(outputs), mrml.transform_matrix(outputs["paPose"]),
                     outputs["paPose"].GetAttribute(mrml.RESULT_ATTRIBUTE), w.ui.statusLabel.text, w._running))

    w._shown = record
    w.ui.applyButton.click()
    assert len(seen) == 1
    preliminary, nodes, matrix, which, status, running = seen[0]
    assert running and which == mrml.PRELIMINARY_RESULT and "Showing the networks' estimate" in status
    cta = mrml.volume_from_node(w._parameterNode.cta)
    np.testing.assert_allclose(matrix, cta.centred_to_ras @ preliminary.poses["pa"], atol=1e-9)
    final = w.logic.outputNodes(w._parameterNode)
    assert all(final[k] is nodes[k] for k in final if k in nodes)  # the same nodes, now at the result
    assert final["paPose"].GetAttribute(mrml.RESULT_ATTRIBUTE) == mrml.FINAL_RESULT and "PA: mNCC" in w.ui.statusLabel.text
    assert scene.GetNodesByName("GeoPose PA pose").GetNumberOfItems() == 1


def test_cancel_after_the_estimate_was_shown_keeps_it_marked_preliminary(newest, phantom):
    """Cancel once the networks' estimate is shown (the TTO running): no error, the parameter node references the
    nodes that show it, their poses still marked preliminary, and the status says the result was not optimised."""
    w = _panel_on_phantom(newest, phantom, iterations=3)
    w._parameterNode.backend = "torch"
    shown = w._shown

    def cancel_when_shown(preliminary, outputs):
        shown(preliminary, outputs)
        w.onCancelButton()

    w._shown = cancel_when_shown
    w.ui.applyButton.click()
    assert w.ui.statusLabel.text == "Cancelled: the output nodes keep the networks' estimate (preliminary, not optimised)."
    kept = w.logic.outputNodes(w._parameterNode)
    assert kept["paPose"].GetAttribute(mrml.RESULT_ATTRIBUTE) == mrml.PRELIMINARY_RESULT and "table" not in kept
    assert w._parameterNode.resultsTable is None and not w.ui.showPAButton.enabled  # no MAP yet
    assert w.ui.applyButton.enabled and not w.ui.cancelButton.enabled


def test_the_gui_processes_events_every_half_second_during_a_registration(newest, phantom):
    """The registration runs off the GUI thread: the GUI thread processes events at least every
    0.5 s from the click to the end (the times Qt's event processing was called, on the phantom
    with the similarity search, Refine and 5 TTO steps: the long stages). Measured on a second
    Apply: the first of a session also loads the library's stages, which holds the interpreter
    (and so the GUI thread) up to about 1 s once (0.98 s measured on 2 busy cores)."""
    import time

    w = _panel_on_phantom(newest, phantom, iterations=5, refineSteps=5)
    w._parameterNode.backend = "torch"
    app = slicer.app
    w.ui.applyButton.click()
    app.processEventsTimes.clear()
    start = time.perf_counter()
    w.ui.applyButton.click()
    end = time.perf_counter()
    times = [start, *app.processEventsTimes, end]
    gaps = np.diff(times)
    assert "PA: mNCC" in w.ui.statusLabel.text and len(times) > 20
    assert gaps.max() < 0.5, f"largest gap {gaps.max():.2f} s at {np.argmax(gaps)} of {len(gaps)} (run {end - start:.1f} s)"


def test_pytorch_is_offered_once_with_what_the_tto_adds(newest, phantom, monkeypatch, installs):
    """Backend "auto" without PyTorch (here: a floor above the installed torch): Apply offers PyTorch
    with what the test-time optimisation adds; a decline registers with onnxruntime, says what was
    skipped, and is not asked again. On Slicer 5.8 (Python 3.9) nothing is offered; the status says why."""
    module = newest
    monkeypatch.setattr(module.dependencies, "TORCH_REQUIREMENT", ">=999")
    runs = _count_registrations(module, monkeypatch)
    w = _panel_on_phantom(module, phantom)
    w._parameterNode.backend = "auto"
    installs["answer"]["ok"] = False
    w.ui.applyButton.click()
    (offer,) = installs["asked"]
    assert offer.startswith(module.dependencies.TTO_BENEFIT) and "mm to" in offer and "vessel segmentation" in offer
    assert runs[-1].backend == "onnxruntime" and "test-time optimisation was skipped" in w.ui.statusLabel.text
    w.ui.applyButton.click()
    assert len(installs["asked"]) == 1 and len(runs) == 2  # asked once
    sys.modules["qt"].QSettings.store.clear()
    installs["answer"]["ok"] = True  # accepted: installed through PyTorchUtils, without a second question
    w.ui.applyButton.click()
    assert installs["torch"] == [{"askConfirmation": False, "torchVersionRequirement": ">=999"}]
    monkeypatch.setattr(module.dependencies, "TORCH_MINIMUM_PYTHON", (99, 0))  # Slicer 5.8
    sys.modules["qt"].QSettings.store.clear()
    w.ui.applyButton.click()
    assert len(installs["asked"]) == 2 and "needs Slicer 5.10 or later" in w.ui.statusLabel.text


# ------------------------------------------------------------------ node roles
def test_a_dsa_runs_shown_frame_is_named_apart_and_never_an_input(module, tmp_path):
    """The volume that shows a run's current frame (the sequence browser's proxy) is named apart from
    the sequence, listed in no input selector, never auto-selected as the CTA; picked from the Python
    console it stands for its sequence, and it is refused as a CTA."""
    from geopose.dsa import DSARun, write_dsa_nifti

    scene = slicer.mrmlScene
    w = H.new_widget(module)
    p = w._parameterNode
    run = DSARun(np.ones((2, DET.rows, DET.cols), np.float32), DET, ANGLES, 100.0)
    path = write_dsa_nifti(run, tmp_path / "pa.nii.gz")
    seq, browser = module.GeoPoseLogic().importDSA(str(path), "PA")
    w.updateSelectorFilters()  # as the scene's node events do
    proxy = browser.GetProxyNode(seq)
    assert (seq.GetName(), proxy.GetName()) == ("DSA PA", "DSA PA (shown frame)")
    assert [n.GetName() for n in scene.GetNodesByName("DSA PA")] == ["DSA PA"]
    assert p.cta is None and w.ui.ctaSelector.currentNode() is None  # the only volume is the shown frame
    assert proxy not in w.ui.dsaPASelector.nodes() and seq in w.ui.dsaPASelector.nodes()
    cta = mrml.volume_to_node(scene, __import__("test_mrml_adapters")._cta()[0], "CTA")
    assert w.ui.ctaSelector.nodes() == [cta] and p.cta is cta  # selected automatically, as Slicer's combo box does
    assert mrml.first_cta_candidate(scene) is cta
    picked = mrml.run_from_node(proxy)
    assert picked.detector == run.detector and picked.angles == run.angles and picked.frames.shape[0] == 2
    with pytest.raises(InputError, match="is a DSA image"):
        module.GeoPoseLogic().register(cta=proxy, dsaPA=seq, dsaLAT=seq)


def test_the_module_has_its_icon_in_the_source_tree(module):
    parent = types.SimpleNamespace(path=str(H.MODULE_FILE))
    module.GeoPose(parent)
    assert Path(parent.icon.path) == H.REPO / "Resources" / "Icons" / "GeoPose.png" and Path(parent.icon.path).is_file()


@pytest.mark.slow
@pytest.mark.parametrize("with_torch", [True, False])
def test_the_self_test_passes_on_the_shipped_case(newest, monkeypatch, tmp_path, with_torch):
    """GeoPoseTest as Slicer's Reload-and-Test runs it, with PyTorch (four registrations: torch and
    onnxruntime, with and without a segmentation) and without (two), on CPU; it leaves no file in
    the temporary folder (a private one here: the machine's is shared) and an empty scene."""
    import tempfile

    module = newest
    if not with_torch:
        monkeypatch.setattr(module.GeoPoseLogic, "torchAvailable", staticmethod(lambda: False))
    registered = _count_registrations(module, monkeypatch)
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    module.GeoPoseTest().runTest()
    assert [(o.backend) for o in registered] == (["torch"] * 2 if with_torch else []) + ["onnxruntime"] * 2
    # torch keeps its own compile cache (torchinductor_<user>) in the temporary folder in any session that uses it
    assert [p for p in temp.iterdir() if not p.name.startswith("torchinductor_")] == []
    assert slicer.mrmlScene.GetNumberOfNodesByClass("vtkMRMLScalarVolumeNode") == 0
