"""GeoPose: CTA-to-DSA C-arm pose estimation, as a 3D Slicer scripted module (Slicer 5.8 or later).

A panel over the ``geopose`` library: ``GeoPoseWidget`` binds the Qt panel to the parameter node,
``GeoPoseLogic`` hands the parameter node's nodes to the library and back (the registration in
``geopose.register``, reading its input nodes and writing its output nodes and results table in
``geopose.mrml``, the Python requirements in ``geopose.dependencies``). At load time only the
library's standard-library modules are imported (``geopose.dependencies``, ``geopose.background``,
``geopose.options``, ``geopose.limits``, ``geopose.errors``, ``geopose.register.progress``), so that
Slicer starts before the Python dependencies are installed. The file runs on Python 3.9 (Slicer 5.8):
no ``X | Y`` annotations, which Slicer's parameter node wrapper evaluates at import.
"""

import contextlib
import dataclasses
import importlib
import logging
import shutil
import sys
from pathlib import Path
from typing import Annotated, Callable, Optional, Union

import qt
import slicer
import vtk
from slicer import (vtkMRMLCameraNode, vtkMRMLLinearTransformNode, vtkMRMLModelNode, vtkMRMLScalarVolumeNode,
                    vtkMRMLSegmentationNode, vtkMRMLSequenceNode, vtkMRMLTableNode)
from slicer.i18n import tr as _
from slicer.i18n import translate
from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper, parameterPack
from slicer.ScriptedLoadableModule import ScriptedLoadableModule, ScriptedLoadableModuleLogic, ScriptedLoadableModuleWidget
from slicer.util import VTKObservationMixin


def _addLibraryPath() -> None:
    """Make ``import GeoPoseTest`` (beside this file) and ``import geopose`` work: the library is installed
    next to this file in the built extension, ``../Logic`` in the source tree."""
    here = Path(__file__).resolve().parent
    if str(here) not in sys.path:
        sys.path.insert(0, str(here))
    for folder in (here, here.parent / "Logic"):
        if (folder / "geopose" / "__init__.py").is_file():
            if str(folder) not in sys.path:
                sys.path.insert(0, str(folder))
            return


_addLibraryPath()

from geopose import background, dependencies  # noqa: E402  (standard library only)
from geopose.errors import InputError  # noqa: E402
from geopose.options import DEVICES, RegistrationOptions, setting_paths  # noqa: E402
from geopose.register.progress import RegistrationCancelled  # noqa: E402


def resourceFile(relative: str) -> Path:
    """A file under ``Resources``: beside this file in the built extension, at the repository root in the source tree."""
    here = Path(__file__).resolve().parent
    for root in (here / "Resources", here.parent / "Resources"):
        if (root / relative).exists():
            return root / relative
    return here / "Resources" / relative


#: The oldest Slicer release the module is tested on (Testing/Python runs it on Slicer
#: 5.8.1's and 5.12.3's Python layer; the library on Python 3.9 with pydicom 2.4.4).
MINIMUM_SLICER = (5, 8)
MINIMUM_SLICER_TEXT = "GeoPose needs 3D Slicer 5.8 or later: install a current release from https://download.slicer.org"
#: Written "First Last (Organisation)", as the Extensions Index requires; equal to EXTENSION_CONTRIBUTORS.
CONTRIBUTORS = ("GeoPose Maintainers (GeoPose for 3D Slicer)",)
#: QSettings key: the user declined the PyTorch offer (not asked again; the PyTorch extension installs it any time).
TORCH_DECLINED_SETTING = "GeoPose/PyTorchDeclined"
#: Seconds between two event-processing calls while a registration runs (the panel stays responsive).
GUI_POLL_S = 0.05
#: View key -> the parameter node's suffix (``dsaPA``, ``outputsLAT``...) and the title of its nodes.
VIEWS = {"pa": "PA", "lat": "LAT"}
#: ``ViewOutputs`` field -> output key suffix (``paPose``, ``latMAP``...; see ``GeoPoseLogic.register``).
OUTPUT_FIELDS = {"pose": "Pose", "camera": "Camera", "frustum": "Frustum", "dsa": "DSA", "map": "MAP", "projection": "Projection"}
#: ``ViewGeometry`` field -> ``geopose.dsa`` geometry key.
GEOMETRY_FIELDS = {"primaryDeg": "primary_deg", "secondaryDeg": "secondary_deg", "sidMm": "sid_mm", "sodMm": "sod_mm",
                   "pixelSpacingMm": "pixel_spacing_mm"}
#: Parameter -> setting of the options tree (``geopose.options``, dotted path): the registration settings the panel
#: holds. Their types, bounds and defaults are the tree's (:func:`withOptionParameters`).
OPTION_FIELDS = {"backend": "backend", "device": "device", "refineSteps": "refine.steps", "iterations": "tto.iterations",
                 "independentViews": "independent_views", "similaritySearch": "search.enabled"}


def withOptionParameters(classtype):
    """``classtype`` given one member per :data:`OPTION_FIELDS` entry, typed, bounded and defaulted as the options
    tree declares that setting (before ``parameterNodeWrapper`` reads the members)."""
    settings = dict(setting_paths())
    for name, path in OPTION_FIELDS.items():
        s = settings[path]
        if s.kind == "bool":
            hint = bool
        elif s.kind == "int":
            hint = Annotated[int, WithinRange(*s.bounds)]
        else:
            hint = Annotated[str, Choice(list(DEVICES if s.kind == "device" else s.choices))]
        classtype.__annotations__[name] = hint
        setattr(classtype, name, s.default)
    return classtype


def checkSlicerVersion() -> None:
    """Raise :class:`InputError` with :data:`MINIMUM_SLICER_TEXT` on a Slicer older than :data:`MINIMUM_SLICER`."""
    if (slicer.app.majorVersion, slicer.app.minorVersion) < MINIMUM_SLICER:
        raise InputError(MINIMUM_SLICER_TEXT)


def runOffGuiThread(work: Callable, progress: Optional[Callable[[str, float, str], None]] = None,
                    deliver: Optional[Callable] = None):
    """``work(report)`` (``work(report, hand_over)`` with ``deliver``) on a worker thread while this (GUI) thread
    processes Qt events every :data:`GUI_POLL_S`, passes the worker's latest ``report(stage, fraction, message)`` on
    to ``progress`` and each ``hand_over(item)`` to ``deliver(item)`` (``geopose.background.run_in_background``):
    Qt and MRML are touched only here, never by ``work``."""
    return background.run_in_background(work, slicer.app.processEvents, GUI_POLL_S, progress, name="GeoPose registration",
                                        deliver=deliver)


class GeoPose(ScriptedLoadableModule):
    """Module description shown in Slicer's module panel and Help."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = _("GeoPose")
        self.parent.categories = [translate("qSlicerAbstractCoreModule", "Registration")]
        self.parent.dependencies = []
        self.parent.contributors = list(CONTRIBUTORS)
        self.parent.helpText = _(
            "Estimates the C-arm pose of a PA and a lateral DSA run relative to a head CTA "
            "(rigid 2D/3D registration): calibrated GeoPose-Init, greedy GeoPose-Refine and "
            "test-time optimisation of a DRR similarity. Outputs one transform, camera and "
            "projected vessel segmentation per view, the DSA runs on their detector planes "
            "and a table of similarity, quality flag and runtimes; Apply again updates the same "
            "output nodes. While the test-time optimisation runs, the output nodes already show the "
            "networks' estimate (their pose transforms marked preliminary). Without PyTorch, Init and "
            "Refine run on onnxruntime with a numpy renderer and the test-time optimisation is skipped. Needs 3D Slicer 5.8 or later; "
            "PyTorch (test-time optimisation) needs Slicer 5.10 or later. "
            "Without a vessel segmentation the arteries are found by a contrast threshold whose "
            "arteries a small classifier keeps (an approximation; on a CTA coarser than 1.5 mm it also "
            "takes enhancing veins; empty for a CT without contrast, then "
            "the pose rests on the DICOM angles and the skull): for the best accuracy select a "
            "segmentation of the arteries on the CTA grid, e.g. painted with the Segment Editor "
            "(Threshold, Islands from the carotids and vertebrals, veins removed) or the artery "
            "labels of a TotalSegmentator run (arteries only: veins in it loosen the fit, and the flag may then "
            "doubt that the CTA is this patient's). The runs must be subtracted: Import DSA subtracts a run archived "
            "native as its own Mask Subtraction Sequence says; export any other native run subtracted."
        )
        self.parent.acknowledgementText = _(
            "Implements the method of: Rudolf L. M. van Herten, Robert Graf, Paula Feldman, "
            "Johannes C. Paetzold. <i>GeoPose: Patient-agnostic CTA-to-DSA registration "
            "through projection-space calibration.</i>"
        )
        # Slicer looks for the icon beside this file (the built extension); in the source tree it is ../Resources.
        self.parent.icon = qt.QIcon(str(resourceFile("Icons/GeoPose.png")))


@parameterPack
class ViewGeometry:
    """Geometry of one DSA view typed into the panel (deg, mm); 0 keeps the file's value
    (angles: used as typed when the overrides are on; ``geopose.mrml.geometry_overrides``)."""

    primaryDeg: Annotated[float, WithinRange(-180.0, 180.0)] = 0.0
    secondaryDeg: Annotated[float, WithinRange(-90.0, 90.0)] = 0.0
    sidMm: Annotated[float, WithinRange(0.0, 3000.0)] = 0.0
    sodMm: Annotated[float, WithinRange(0.0, 3000.0)] = 0.0
    pixelSpacingMm: Annotated[float, WithinRange(0.0, 5.0)] = 0.0


@parameterPack
class ViewOutputs:
    """Output nodes of one view: chosen in the panel or created by the first Apply, updated in place after."""

    pose: vtkMRMLLinearTransformNode
    camera: vtkMRMLCameraNode
    frustum: vtkMRMLModelNode
    dsa: vtkMRMLSequenceNode
    map: vtkMRMLScalarVolumeNode
    projection: vtkMRMLSegmentationNode


@parameterNodeWrapper
@withOptionParameters
class GeoPoseParameterNode:
    """Inputs, options (:data:`OPTION_FIELDS`, generated from the options tree) and output references
    of one registration (saved with the scene)."""

    cta: vtkMRMLScalarVolumeNode
    craniumMask: vtkMRMLSegmentationNode
    segmentation: vtkMRMLSegmentationNode
    dsaPA: Union[vtkMRMLSequenceNode, vtkMRMLScalarVolumeNode, None]
    dsaLAT: Union[vtkMRMLSequenceNode, vtkMRMLScalarVolumeNode, None]
    overrideGeometry: bool = False
    geometryPA: ViewGeometry
    geometryLAT: ViewGeometry
    outputsPA: ViewOutputs
    outputsLAT: ViewOutputs
    resultsTable: vtkMRMLTableNode


class GeoPoseWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """The panel (Qt): inputs, overrides, options, outputs, Apply/Cancel with progress, results."""

    #: The parts of the panel locked while a registration runs (everything but Cancel and the progress).
    LOCKED_WHILE_RUNNING = ("inputsCollapsibleButton", "geometryCollapsibleButton", "optionsCollapsibleButton",
                            "outputsCollapsibleButton", "showPAButton", "showLATButton")

    def __init__(self, parent=None) -> None:
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._untaggedGuiNode = None
        self._cancelRequested = False
        self._running = False
        self._shownText = ""
        self._shownOutputs = None

    def setup(self) -> None:
        ScriptedLoadableModuleWidget.setup(self)
        try:
            checkSlicerVersion()
        except InputError as exc:
            self.layout.addWidget(qt.QLabel(str(exc)))
            return
        uiWidget = slicer.util.loadUI(str(resourceFile("UI/GeoPose.ui")))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = GeoPoseLogic()

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        for event in (slicer.mrmlScene.NodeAddedEvent, slicer.mrmlScene.NodeRemovedEvent):
            self.addObserver(slicer.mrmlScene, event, self.updateSelectorFilters)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.cancelButton.connect("clicked(bool)", self.onCancelButton)
        self.ui.importPAButton.connect("clicked(bool)", lambda: self.onImportDSA("pa"))
        self.ui.importLATButton.connect("clicked(bool)", lambda: self.onImportDSA("lat"))
        self.ui.showPAButton.connect("clicked(bool)", lambda: self.onShowView("pa"))
        self.ui.showLATButton.connect("clicked(bool)", lambda: self.onShowView("lat"))
        self.ui.cancelButton.enabled = False
        self.ui.progressBar.hide()
        self.updateSelectorFilters()
        self.initializeParameterNode()

    def cleanup(self) -> None:
        self.removeObservers()

    def enter(self) -> None:
        if self.logic is not None:
            self.initializeParameterNode()

    def exit(self) -> None:
        if self._parameterNode:
            self._disconnectGui()
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)

    def onSceneStartClose(self, caller, event) -> None:
        self._cancelRequested = True  # a running registration stops; its outputs would belong to the closed scene
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event) -> None:
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self) -> None:
        from geopose import mrml

        self.setParameterNode(self.logic.getParameterNode())
        if not self._parameterNode.cta:
            self._parameterNode.cta = mrml.first_cta_candidate(slicer.mrmlScene)

    def updateSelectorFilters(self, caller=None, event=None) -> None:
        """Hide the volumes that show a sequence's current frame (browser proxies) from the input
        selectors, and DSA images (detector-plane volumes) from the CTA selector, through the
        selectors' own filter (``sortFilterProxyModel().hiddenNodeIDs``)."""
        from geopose import mrml

        proxies = mrml.sequence_proxy_ids(slicer.mrmlScene)
        self.ui.ctaSelector.sortFilterProxyModel().hiddenNodeIDs = proxies + mrml.dsa_image_ids(slicer.mrmlScene)
        for selector in (self.ui.dsaPASelector, self.ui.dsaLATSelector, self.ui.craniumMaskSelector, self.ui.segmentationSelector):
            selector.sortFilterProxyModel().hiddenNodeIDs = proxies

    def setParameterNode(self, inputParameterNode: Optional[GeoPoseParameterNode]) -> None:
        if self._parameterNode:
            self._disconnectGui()
            if self.hasObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply):
                self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
        self._parameterNode = inputParameterNode
        if self._parameterNode:
            self._connectGui()
            self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
            self._checkCanApply()

    def _connectGui(self) -> None:
        """Connect the panel to the parameter node. Slicer 5.8's ``connectGui`` returns no tag, so its
        connections cannot be removed: there each node is connected once and stays connected."""
        node = self._parameterNode.parameterNode
        if node is not self._untaggedGuiNode:
            self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
            self._untaggedGuiNode = node if self._parameterNodeGuiTag is None else None

    def _disconnectGui(self) -> None:
        if self._parameterNodeGuiTag is not None:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None

    def _checkCanApply(self, caller=None, event=None) -> None:
        """Apply is enabled when the inputs are chosen and no registration runs (the parameter node
        can change during a run: from the Python console, or a scene event)."""
        p = self._parameterNode
        ready = bool(p and p.cta and p.dsaPA and p.dsaLAT)
        self.ui.applyButton.enabled = ready and not self._running
        self.ui.applyButton.toolTip = _("Register the CTA to both DSA runs") if ready else _(
            "Select a CTA volume and a PA and a lateral DSA run"
        )
        self.ui.showPAButton.enabled = bool(p and p.outputsPA.map) and not self._running
        self.ui.showLATButton.enabled = bool(p and p.outputsLAT.map) and not self._running

    def _setRunning(self, running: bool) -> None:
        """Lock the panel except Cancel while a registration runs; unlock it after."""
        self._running = running
        for name in self.LOCKED_WHILE_RUNNING:
            getattr(self.ui, name).enabled = not running
        self.ui.cancelButton.enabled = running
        self.ui.progressBar.visible = running
        if running:
            self.ui.progressBar.value = 0
        self._checkCanApply()

    @contextlib.contextmanager
    def _errorDisplay(self, failure: str, waitCursor: bool = True):
        """A user error (:class:`InputError`) is shown as its one line, a cancelled registration as a status
        line (no dialog); anything else as Slicer shows errors (with details)."""
        with slicer.util.tryWithErrorDisplay(failure, waitCursor=waitCursor):
            try:
                yield
            except InputError as exc:
                self.ui.statusLabel.text = str(exc)
                slicer.util.errorDisplay(str(exc), windowTitle=failure)
            except RegistrationCancelled:
                self.ui.statusLabel.text = self._keepShownOnCancel()

    def _keepShownOnCancel(self) -> str:
        """After a cancelled registration: the output nodes that show its networks' estimate, if it got that far,
        are referenced from the parameter node (their poses stay marked preliminary). Returns the status line."""
        if self._shownOutputs is None:
            return _("Cancelled: no output node was changed.")
        self.logic.setOutputNodes(self._parameterNode, self._shownOutputs)
        return _("Cancelled: the output nodes keep the networks' estimate (preliminary, not optimised).")

    def onImportDSA(self, key: str) -> None:
        path = qt.QFileDialog.getOpenFileName(
            slicer.util.mainWindow(), _("Import DSA run"), "", _("DSA (*.dcm *.nii *.nii.gz);;All files (*)")
        )
        if not path:
            return
        with self._errorDisplay(_("Could not import the DSA run.")):
            if not self.logic.ensureDependencies(askUser=True):
                return
            overrides = self.logic.overridesFromParameters(self._parameterNode, key)
            sequence, _browser = self.logic.importDSA(path, VIEWS[key], ctaNode=self._parameterNode.cta, **overrides)
            setattr(self._parameterNode, "dsa" + VIEWS[key], sequence)

    def onCancelButton(self) -> None:
        if self._running:
            self._cancelRequested = True
            self.ui.statusLabel.text = _("Cancelling after the current step...")

    def _progress(self, stage: str, fraction: float, message: str) -> None:
        """Progress of the running registration (called on the GUI thread, see :func:`runOffGuiThread`)."""
        if self._cancelRequested:
            return  # the status says "Cancelling..." until the worker stops
        self.ui.progressBar.value = int(100 * fraction)
        self.ui.statusLabel.text = "\n".join(s for s in (self._shownText, f"{stage}: {message}") if s)

    def _shown(self, preliminary, outputs: dict) -> None:
        """The networks' estimate is in the output nodes (called on the GUI thread while the registration goes on)."""
        self._shownText = _("Showing the networks' estimate ({seconds:.1f} s); the test-time optimisation refines it.").format(
            seconds=preliminary.elapsed_s)
        self._shownOutputs = dict(outputs)
        self.ui.statusLabel.text = self._shownText

    def onApplyButton(self) -> None:
        """Register with the panel's inputs and options. The computation runs off the GUI thread
        (:func:`runOffGuiThread`): the application stays responsive, the panel is locked except
        Cancel, and a click that re-enters here while a run goes on is ignored."""
        if self._running:
            return
        p = self._parameterNode
        self._cancelRequested = False
        self._shownText, self._shownOutputs = "", None
        self._setRunning(True)
        self.ui.statusLabel.text = _("Starting the registration...")
        try:
            with self._errorDisplay(_("Registration failed."), waitCursor=False):
                options = self.logic.optionsFromParameters(p)
                if not self.logic.ensureDependencies(askUser=True, torch=options.backend == "torch"):
                    self.ui.statusLabel.text = _("Nothing was installed, so the registration did not run.")
                    return
                torchNote = ""
                if options.backend == "auto":
                    options, torchNote = self.logic.offerTorch(options, askUser=True)
                outputs = self.logic.register(
                    cta=p.cta, dsaPA=p.dsaPA, dsaLAT=p.dsaLAT, segmentation=p.segmentation, craniumMask=p.craniumMask,
                    options=options, overridesPA=self.logic.overridesFromParameters(p, "pa"),
                    overridesLAT=self.logic.overridesFromParameters(p, "lat"), outputs=self.logic.outputNodes(p),
                    progress=self._progress, cancel=lambda: self._cancelRequested, offGuiThread=True, shown=self._shown,
                )
                self.logic.setOutputNodes(p, outputs)
                self.ui.resultsTableView.setMRMLTableNode(outputs["table"])
                self.ui.statusLabel.text = "\n".join(s for s in (self.logic.summary(outputs), torchNote) if s)
        finally:
            self._setRunning(False)

    def onShowView(self, key: str) -> None:
        """Red slice view on the detector plane (MAP + projected vessels); 3D view through the C-arm."""
        from geopose import mrml

        views = getattr(self._parameterNode, "outputs" + VIEWS[key])
        if views.map is None:
            return
        slicer.util.setSliceViewerLayers(background=views.map, fit=False)
        if views.projection is not None:
            views.projection.GetDisplayNode().SetVisibility(True)
        sliceWidget = slicer.app.layoutManager().sliceWidget("Red")
        normal, column, centre = mrml.plane_axes(views.map)
        sliceWidget.mrmlSliceNode().SetSliceToRASByNTP(*normal, *column, *centre, 0)
        sliceWidget.sliceLogic().FitSliceToAll()
        threeD = slicer.app.layoutManager().threeDWidget(0)
        if views.camera is not None and threeD is not None:
            threeD.threeDView().cameraNode().GetCamera().DeepCopy(views.camera.GetCamera())


class GeoPoseLogic(ScriptedLoadableModuleLogic):
    """MRML <-> ``geopose`` adapter; usable from the Python console without the GUI:

    ``GeoPoseLogic().register(cta=ctaNode, dsaPA=paSeq, dsaLAT=latSeq, segmentation=segNode)``
    returns a dict of the output nodes; pass it back as ``outputs=`` to update them in place.
    """

    def getParameterNode(self) -> GeoPoseParameterNode:
        return GeoPoseParameterNode(super().getParameterNode())

    # ------------------------------------------------------------ dependencies (geopose.dependencies)

    @staticmethod
    def torchAvailable() -> bool:
        """Whether PyTorch at ``dependencies.TORCH_REQUIREMENT`` or newer imports here."""
        return dependencies.torch_available()

    def ensureDependencies(self, askUser: bool = True, torch: bool = False) -> bool:
        """Install the unmet ``dependencies.SLICER_REQUIREMENTS`` (and, with ``torch``, PyTorch through the
        PyTorch extension), asking first when ``askUser``. Returns False when the user declines; raises
        :class:`InputError` when something cannot be installed here. Nothing Slicer ships is changed
        (``dependencies.install_missing``); never installs in Slicer's testing mode."""
        checkSlicerVersion()

        def ask(plan) -> bool:
            return slicer.util.confirmOkCancelDisplay(
                _("GeoPose needs Python packages that are not installed. These versions fit this Slicer's own "
                  "packages (none of which is changed) and will be downloaded and installed now:\n\n")
                + "\n".join(f"{name} {version}" for name, version in plan), windowTitle=_("GeoPose - Install Python packages"))

        def pip(requirements, constraints) -> None:
            try:
                packaging = importlib.import_module("slicer.packaging")  # Slicer 5.12 and later
            except ImportError:
                slicer.util.pip_install(["-c", str(constraints), *requirements])
            else:
                packaging.pip_ensure(requirements, constraints=constraints, prompt_install=False, requester="GeoPose")

        python = shutil.which("PythonSlicer") or sys.executable  # the Python that runs pip for Slicer
        if not dependencies.install_missing(python, pip, ask if askUser else None, slicer.app.testingEnabled()):
            return False
        return self._installTorch(askUser) if torch and not self.torchAvailable() else True

    def offerTorch(self, options: RegistrationOptions, askUser: bool = True):
        """For backend ``auto`` without PyTorch: offer it once (``dependencies.TTO_BENEFIT``; a decline is
        remembered in the settings), through the PyTorch extension. Returns ``(options, note)``: the
        options the registration runs with (backend ``onnxruntime`` when PyTorch stays missing) and a
        line for the user saying what was skipped and how to get it ("" with PyTorch)."""
        if self.torchAvailable():
            return options, ""
        withoutTorch = dataclasses.replace(options, backend="onnxruntime")
        if not dependencies.torch_supported():
            return withoutTorch, _("The test-time optimisation was skipped: it needs PyTorch, which needs Slicer 5.10 "
                                   "or later.")
        later = _("The test-time optimisation was skipped: to add it, install PyTorch by running "
                  "'import GeoPose; GeoPose.GeoPoseLogic().ensureDependencies(torch=True)' in the Python console.")
        settings = qt.QSettings()
        if not askUser or settings.value(TORCH_DECLINED_SETTING, False) in (True, "true"):
            return withoutTorch, later
        if not slicer.util.confirmOkCancelDisplay(
            dependencies.TTO_BENEFIT + "\n\n" + _("Install PyTorch now (through the PyTorch extension)? Cancel registers "
                                                  "without the test-time optimisation and does not ask again."),
            windowTitle=_("GeoPose - PyTorch"),
        ):
            settings.setValue(TORCH_DECLINED_SETTING, True)
            return withoutTorch, later
        try:
            installed = self._installTorch(askUser=False)
        except InputError as exc:
            return withoutTorch, _("The test-time optimisation was skipped: ") + str(exc)
        return (options, "") if installed else (withoutTorch, later)

    def _installTorch(self, askUser: bool) -> bool:
        requirement = dependencies.TORCH_REQUIREMENT
        if not dependencies.torch_supported():
            raise InputError(
                f"backend 'torch' needs PyTorch {requirement}, which needs Slicer 5.10 or later (Python 3.10+); "
                "choose backend 'auto' or 'onnxruntime' (Init + Refine without test-time optimisation)"
            )
        try:
            import PyTorchUtils
        except ImportError:
            raise InputError(
                "backend 'torch' needs the PyTorch extension: install 'PyTorch' in the Extensions Manager and restart "
                "Slicer, or choose backend 'auto' or 'onnxruntime' (Init + Refine without test-time optimisation)"
            ) from None
        if PyTorchUtils.PyTorchUtilsLogic().installTorch(askConfirmation=askUser, torchVersionRequirement=requirement) is None:
            return False  # declined
        importlib.invalidate_caches()
        return self.torchAvailable()

    # ------------------------------------------------------------ parameter node <-> library

    @staticmethod
    def optionsFromParameters(p: GeoPoseParameterNode) -> RegistrationOptions:
        """The registration settings of the panel (:data:`OPTION_FIELDS`)."""
        return RegistrationOptions().replace(**{path: getattr(p, name) for name, path in OPTION_FIELDS.items()})

    @staticmethod
    def overridesFromParameters(p: GeoPoseParameterNode, key: str) -> dict:
        """Geometry overrides (``geopose.dsa`` key names) from the panel; empty when not enabled."""
        from geopose import mrml

        if not p.overrideGeometry:
            return {}
        geometry = getattr(p, "geometry" + VIEWS[key])
        return mrml.geometry_overrides({field: getattr(geometry, name) for name, field in GEOMETRY_FIELDS.items()})

    @staticmethod
    def outputNodes(p: GeoPoseParameterNode) -> dict:
        """The output nodes the parameter node references, by output key (see :meth:`register`)."""
        found = {"table": p.resultsTable}
        for key, title in VIEWS.items():
            views = getattr(p, "outputs" + title)
            found.update({key + suffix: getattr(views, field) for field, suffix in OUTPUT_FIELDS.items()})
        return {k: node for k, node in found.items() if node is not None}

    @staticmethod
    def setOutputNodes(p: GeoPoseParameterNode, outputs: dict) -> None:
        """Reference the output nodes of :meth:`register` from the parameter node (saved with the scene); without a
        table (the nodes of a preliminary result) none is referenced."""
        with slicer.util.NodeModify(p):
            p.resultsTable = outputs.get("table")
            for key, title in VIEWS.items():
                for field, suffix in OUTPUT_FIELDS.items():
                    setattr(getattr(p, "outputs" + title), field, outputs.get(key + suffix))

    # ------------------------------------------------------------ registration

    def importDSA(self, path: str, title: str, ctaNode=None, **overrides):
        """Read a DSA run (DICOM XA, or NIfTI + JSON sidecar) into a sequence node ``DSA <title>`` placed on
        its nominal detector plane (C-arm angles about the CTA grid centre). Returns (sequence, browser)."""
        checkSlicerVersion()
        from geopose import mrml

        return mrml.read_dsa_node(slicer.mrmlScene, path, f"DSA {title}", reference=ctaNode, **overrides)

    @staticmethod
    def defaultModelsFolder() -> Path:
        """Shipped models: ``Resources/Models`` beside this file (built) or at the repository root."""
        return resourceFile("Models")

    def register(self, cta, dsaPA, dsaLAT, segmentation=None, craniumMask=None, options: Optional[RegistrationOptions] = None,
                 models=None, overridesPA: Optional[dict] = None, overridesLAT: Optional[dict] = None,
                 outputs: Optional[dict] = None, progress: Optional[Callable[[str, float, str], None]] = None,
                 cancel: Optional[Callable[[], bool]] = None, offGuiThread: bool = False,
                 shown: Optional[Callable] = None) -> dict:
        """Register ``cta`` (scalar volume, HU) to the PA and lateral DSA runs (sequence or
        volume nodes) with ``options`` (default ``RegistrationOptions()``). Input nodes are not
        modified. Returns the output nodes by key: ``{pa,lat}{Pose,Camera,Frustum,DSA,DSABrowser,
        MAP,Projection}`` and ``table``, plus ``result`` (the library's in-memory result) and
        ``record`` (the JSON-ready record that ``geopose register`` writes as result.json).
        ``outputs``: existing output nodes by the same keys (e.g. the previous return value),
        updated in place instead of new ones. ``offGuiThread``: the computation (between reading the
        input nodes and writing the output nodes, which stay on this thread) runs on a worker thread
        while this thread processes Qt events (:func:`runOffGuiThread`); ``progress`` is then called
        on this thread, and the output nodes show the networks' estimate as soon as it exists (their pose
        transforms' ``GeoPose.result`` attribute says "preliminary" until the end), after which
        ``shown(preliminary, outputs)`` is called."""
        checkSlicerVersion()
        options = options if options is not None else RegistrationOptions()
        if options.backend == "torch" and not self.torchAvailable():
            raise InputError(
                f"backend 'torch' was asked for but PyTorch {dependencies.TORCH_REQUIREMENT} is not installed: install "
                "the PyTorch extension (or run GeoPoseLogic().ensureDependencies(torch=True) from the Python console), "
                "or use backend 'onnxruntime' for Init + Refine without test-time optimisation"
            )
        from geopose import mrml

        out = mrml.register_nodes(
            slicer.mrmlScene, cta, dsaPA, dsaLAT, segmentation, craniumMask, options, models or self.defaultModelsFolder(),
            overrides={"pa": overridesPA, "lat": overridesLAT}, outputs=outputs, progress=progress, cancel=cancel,
            run=runOffGuiThread if offGuiThread else None, tick=slicer.app.processEvents if offGuiThread else None,
            shown=shown)
        for note in out["result"].notes:
            logging.warning(note)
        return out

    @staticmethod
    def summary(outputs: dict) -> str:
        """One line per view: mNCC and quality flag (from the result table)."""
        from geopose import mrml

        return mrml.result_summary(outputs["table"]) if outputs.get("table") is not None else ""


# Slicer's "Reload and Test" and Testing/CMakeLists.txt run the self-test as GeoPose.GeoPoseTest (beside this file).
from GeoPoseTest import GeoPoseTest  # noqa: E402,F401
