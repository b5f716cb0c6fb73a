"""GeoPose: CTA-to-DSA C-arm pose estimation, as a 3D Slicer scripted module.

``GeoPoseLogic`` only adapts MRML nodes to the ``geopose`` library (registration
in ``geopose.register``, node conversions in ``geopose.mrml``); everything that
needs Qt lives in ``GeoPoseWidget``. The library is imported lazily so that
Slicer starts even before the Python dependencies are installed.
"""

import importlib.util
import logging
import math
import sys
from pathlib import Path
from typing import Annotated, Callable, Optional, Union

import slicer
from slicer import vtkMRMLScalarVolumeNode, vtkMRMLSegmentationNode, vtkMRMLSequenceNode
from slicer.i18n import tr as _
from slicer.i18n import translate
from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper
from slicer.ScriptedLoadableModule import (
    ScriptedLoadableModule,
    ScriptedLoadableModuleLogic,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
)
from slicer.util import VTKObservationMixin


def _addLibraryPath() -> None:
    """Make ``import geopose`` work: installed next to this file in the built extension,
    ``../Logic`` in the source tree."""
    here = Path(__file__).resolve().parent
    for folder in (here, here.parent / "Logic"):
        if (folder / "geopose" / "__init__.py").is_file():
            if str(folder) not in sys.path:
                sys.path.insert(0, str(folder))
            return


_addLibraryPath()


def resourceFile(relative: str) -> Path:
    """A file under ``Resources``: beside this file in the built extension, at the repository root in the source tree."""
    here = Path(__file__).resolve().parent
    for root in (here / "Resources", here.parent / "Resources"):
        if (root / relative).exists():
            return root / relative
    return here / "Resources" / relative

#: (import name, pip requirement) of the runtime dependencies besides torch.
REQUIREMENTS = (
    ("SimpleITK", "SimpleITK>=2.3"),
    ("pydicom", "pydicom>=3.0"),
    ("pylibjpeg", "pylibjpeg>=2.0"),
    ("libjpeg", "pylibjpeg-libjpeg>=2.1"),
    ("openjpeg", "pylibjpeg-openjpeg>=2.3"),
    ("rle", "pylibjpeg-rle>=2.0"),
    ("onnx", "onnx>=1.16"),
    ("onnxruntime", "onnxruntime>=1.18"),
)
#: Network backends: auto = torch when installed, else onnxruntime with the numpy renderer.
BACKENDS = ("auto", "torch", "onnxruntime")
VIEW_KEYS = ("pa", "lat")
VIEW_TITLES = {"pa": "PA", "lat": "LAT"}
#: Geometry override keys (``geopose.dsa.GEOMETRY_KEYS`` names) shown in the panel.
OVERRIDE_KEYS = ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_spacing_mm")


#
# GeoPose
#


class GeoPose(ScriptedLoadableModule):
    """Module description shown in Slicer's module panel and Help."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = _("GeoPose")
        self.parent.categories = [translate("qSlicerAbstractCoreModule", "Registration")]
        self.parent.dependencies = []
        self.parent.contributors = ["GeoPose for 3D Slicer contributors"]
        self.parent.helpText = _(
            "Estimates the C-arm pose of a PA and a lateral DSA run relative to a head CTA "
            "(rigid 2D/3D registration): calibrated GeoPose-Init, greedy GeoPose-Refine and "
            "test-time optimisation of a DRR similarity. Outputs one transform, camera and "
            "projected vessel segmentation per view, the DSA runs on their detector planes "
            "and a table of similarity, quality flag and runtimes. Without PyTorch, Init and "
            "Refine run on onnxruntime with a numpy renderer and the test-time optimisation is skipped."
        )
        self.parent.acknowledgementText = _(
            "Implements the method of: Rudolf L. M. van Herten, Robert Graf, Paula Feldman, "
            "Johannes C. Paetzold. <i>GeoPose: Patient-agnostic CTA-to-DSA registration "
            "through projection-space calibration.</i>"
        )


#
# GeoPoseParameterNode
#


@parameterNodeWrapper
class GeoPoseParameterNode:
    """Inputs and options of one registration (saved with the scene)."""

    cta: vtkMRMLScalarVolumeNode
    craniumMask: vtkMRMLSegmentationNode
    segmentation: vtkMRMLSegmentationNode
    dsaPA: Union[vtkMRMLSequenceNode, vtkMRMLScalarVolumeNode]
    dsaLAT: Union[vtkMRMLSequenceNode, vtkMRMLScalarVolumeNode]
    overrideGeometry: bool = False
    primaryDegPA: Annotated[float, WithinRange(-180.0, 180.0)] = 0.0
    secondaryDegPA: Annotated[float, WithinRange(-90.0, 90.0)] = 0.0
    sidMmPA: Annotated[float, WithinRange(0.0, 3000.0)] = 0.0
    sodMmPA: Annotated[float, WithinRange(0.0, 3000.0)] = 0.0
    pixelSpacingMmPA: Annotated[float, WithinRange(0.0, 5.0)] = 0.0
    primaryDegLAT: Annotated[float, WithinRange(-180.0, 180.0)] = 0.0
    secondaryDegLAT: Annotated[float, WithinRange(-90.0, 90.0)] = 0.0
    sidMmLAT: Annotated[float, WithinRange(0.0, 3000.0)] = 0.0
    sodMmLAT: Annotated[float, WithinRange(0.0, 3000.0)] = 0.0
    pixelSpacingMmLAT: Annotated[float, WithinRange(0.0, 5.0)] = 0.0
    device: Annotated[str, Choice(["auto", "cpu", "cuda"])] = "auto"
    refineSteps: Annotated[int, WithinRange(0, 20)] = 5
    iterations: Annotated[int, WithinRange(0, 1000)] = 25
    backend: Annotated[str, Choice(list(BACKENDS))] = "auto"


#
# GeoPoseWidget
#


class GeoPoseWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """The panel (Qt): inputs, overrides, options, Apply/Cancel with progress, results."""

    def __init__(self, parent=None) -> None:
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._cancelRequested = False
        self._outputs: dict = {}

    def setup(self) -> None:
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(str(resourceFile("UI/GeoPose.ui")))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = GeoPoseLogic()

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.cancelButton.connect("clicked(bool)", self.onCancelButton)
        self.ui.importPAButton.connect("clicked(bool)", lambda: self.onImportDSA("pa"))
        self.ui.importLATButton.connect("clicked(bool)", lambda: self.onImportDSA("lat"))
        self.ui.showPAButton.connect("clicked(bool)", lambda: self.onShowView("pa"))
        self.ui.showLATButton.connect("clicked(bool)", lambda: self.onShowView("lat"))
        self.ui.cancelButton.enabled = False
        self.ui.progressBar.hide()
        self.initializeParameterNode()

    def cleanup(self) -> None:
        self.removeObservers()

    def enter(self) -> None:
        self.initializeParameterNode()

    def exit(self) -> None:
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            self.removeObserver(self._parameterNode, vtk_ModifiedEvent(), self._checkCanApply)

    def onSceneStartClose(self, caller, event) -> None:
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event) -> None:
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self) -> None:
        self.setParameterNode(self.logic.getParameterNode())
        if not self._parameterNode.cta:
            self._parameterNode.cta = slicer.mrmlScene.GetFirstNodeByClass("vtkMRMLScalarVolumeNode")

    def setParameterNode(self, inputParameterNode: Optional[GeoPoseParameterNode]) -> None:
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self.removeObserver(self._parameterNode, vtk_ModifiedEvent(), self._checkCanApply)
        self._parameterNode = inputParameterNode
        if self._parameterNode:
            self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
            self.addObserver(self._parameterNode, vtk_ModifiedEvent(), self._checkCanApply)
            self._checkCanApply()

    def _checkCanApply(self, caller=None, event=None) -> None:
        p = self._parameterNode
        ready = bool(p and p.cta and p.dsaPA and p.dsaLAT)
        self.ui.applyButton.enabled = ready
        self.ui.applyButton.toolTip = _("Register the CTA to both DSA runs") if ready else _(
            "Select a CTA volume and a PA and a lateral DSA run"
        )

    def onImportDSA(self, key: str) -> None:
        import qt

        path = qt.QFileDialog.getOpenFileName(
            slicer.util.mainWindow(), _("Import DSA run"), "", _("DSA (*.dcm *.nii *.nii.gz);;All files (*)")
        )
        if not path:
            return
        with slicer.util.tryWithErrorDisplay(_("Could not import the DSA run."), waitCursor=True):
            if not self.logic.ensureDependencies(askUser=True):
                return
            overrides = self.logic.overridesFromParameters(self._parameterNode, key)
            sequence, _browser = self.logic.importDSA(path, VIEW_TITLES[key], ctaNode=self._parameterNode.cta, **overrides)
            setattr(self._parameterNode, "dsaPA" if key == "pa" else "dsaLAT", sequence)

    def onCancelButton(self) -> None:
        self._cancelRequested = True
        self.ui.statusLabel.text = _("Cancelling after the current step...")

    def _progress(self, stage: str, fraction: float, message: str) -> None:
        import qt

        self.ui.progressBar.value = int(100 * fraction)
        self.ui.statusLabel.text = f"{stage}: {message}"
        qt.QApplication.processEvents()

    def onApplyButton(self) -> None:
        p = self._parameterNode
        self._cancelRequested = False
        self.ui.applyButton.enabled = False
        self.ui.cancelButton.enabled = True
        self.ui.progressBar.show()
        try:
            with slicer.util.tryWithErrorDisplay(_("Registration failed."), waitCursor=True):
                if not self.logic.ensureDependencies(askUser=True, torch=p.backend == "torch"):
                    return
                iterations = p.iterations
                self._outputs = self.logic.register(
                    cta=p.cta,
                    dsaPA=p.dsaPA,
                    dsaLAT=p.dsaLAT,
                    segmentation=p.segmentation,
                    craniumMask=p.craniumMask,
                    iterations=iterations,
                    refineSteps=p.refineSteps,
                    device=p.device,
                    backend=p.backend,
                    overridesPA=self.logic.overridesFromParameters(p, "pa"),
                    overridesLAT=self.logic.overridesFromParameters(p, "lat"),
                    progress=self._progress,
                    cancel=lambda: self._cancelRequested,
                )
                self._showResults()
        finally:
            self.ui.cancelButton.enabled = False
            self.ui.progressBar.hide()
            self._checkCanApply()

    def _showResults(self) -> None:
        table = self._outputs.get("table")
        self.ui.resultsTableView.setMRMLTableNode(table)
        self.ui.statusLabel.text = self.logic.summary(self._outputs)
        self.ui.showPAButton.enabled = "paMAP" in self._outputs
        self.ui.showLATButton.enabled = "latMAP" in self._outputs

    def onShowView(self, key: str) -> None:
        """Red slice view on the detector plane (MAP + projected vessels); 3D view through the C-arm."""
        mapNode = self._outputs.get(f"{key}MAP")
        if mapNode is None:
            return
        slicer.util.setSliceViewerLayers(background=mapNode, fit=False)
        projection = self._outputs.get(f"{key}Projection")
        if projection is not None:
            projection.GetDisplayNode().SetVisibility(True)
        sliceNode = slicer.app.layoutManager().sliceWidget("Red").mrmlSliceNode()
        normal, column, centre = self.logic.planeAxes(mapNode)
        sliceNode.SetSliceToRASByNTP(*normal, *column, *centre, 0)
        slicer.app.layoutManager().sliceWidget("Red").sliceLogic().FitSliceToAll()
        camera = self._outputs.get(f"{key}Camera")
        threeD = slicer.app.layoutManager().threeDWidget(0)
        if camera is not None and threeD is not None:
            threeD.threeDView().cameraNode().GetCamera().DeepCopy(camera.GetCamera())


def vtk_ModifiedEvent() -> int:
    import vtk

    return vtk.vtkCommand.ModifiedEvent


#
# GeoPoseLogic
#


class GeoPoseLogic(ScriptedLoadableModuleLogic):
    """MRML <-> ``geopose`` adapter; usable from the Python console without the GUI:

    ``GeoPoseLogic().register(cta=ctaNode, dsaPA=paSeq, dsaLAT=latSeq, segmentation=segNode)``
    returns a dict of the output nodes.
    """

    def __init__(self) -> None:
        ScriptedLoadableModuleLogic.__init__(self)

    def getParameterNode(self) -> GeoPoseParameterNode:
        return GeoPoseParameterNode(super().getParameterNode())

    # ------------------------------------------------------------ dependencies

    @staticmethod
    def torchAvailable() -> bool:
        """Whether PyTorch imports here (a broken install counts as missing)."""
        try:
            import torch  # noqa: F401
        except (ImportError, OSError):
            return False
        return True

    def missingRequirements(self) -> list[str]:
        return [req for module, req in REQUIREMENTS if importlib.util.find_spec(module) is None]

    def ensureDependencies(self, askUser: bool = True, torch: bool = True) -> bool:
        """Install missing packages with Slicer's own installer after asking; torch through the
        PyTorch extension when present. Returns False if the user declined."""
        missing = self.missingRequirements()
        if missing:
            packaging = getattr(slicer, "packaging", None)
            if packaging is not None and hasattr(packaging, "pip_ensure"):  # Slicer 5.12+
                packaging.pip_ensure(missing, requester="GeoPose")
            else:
                if askUser and not slicer.util.confirmOkCancelDisplay(
                    _("GeoPose needs these Python packages, which will be downloaded and installed now:\n")
                    + "\n".join(missing)
                ):
                    return False
                slicer.util.pip_install(missing)
        if torch and not self.torchAvailable():
            try:
                import PyTorchUtils
            except ImportError:
                if askUser and not slicer.util.confirmOkCancelDisplay(
                    _("PyTorch is needed to render the CTA (calibration, refinement, test-time optimisation). Install it now? "
                      "(Installing the PyTorch extension gives a choice of CUDA versions.)")
                ):
                    return self.torchAvailable() or not torch
                slicer.util.pip_install("torch")
            else:
                torchLogic = PyTorchUtils.PyTorchUtilsLogic()
                if not torchLogic.torchInstalled():
                    torchLogic.installTorch(askConfirmation=askUser)
        return True

    # ------------------------------------------------------------ inputs

    @staticmethod
    def overridesFromParameters(p: GeoPoseParameterNode, key: str) -> dict:
        """Geometry overrides (``geopose.dsa`` key names) from the panel; empty when not enabled."""
        if not p.overrideGeometry:
            return {}
        suffix = VIEW_TITLES[key]
        values = {
            "primary_deg": getattr(p, f"primaryDeg{suffix}"),
            "secondary_deg": getattr(p, f"secondaryDeg{suffix}"),
            "sid_mm": getattr(p, f"sidMm{suffix}"),
            "sod_mm": getattr(p, f"sodMm{suffix}"),
            "pixel_spacing_mm": getattr(p, f"pixelSpacingMm{suffix}"),
        }
        out = {k: v for k, v in values.items() if k.endswith("_deg") or v > 0}
        if "pixel_spacing_mm" in out:
            out["pixel_spacing_mm"] = (out["pixel_spacing_mm"], out["pixel_spacing_mm"])
        return out

    @staticmethod
    def _scene():
        return slicer.mrmlScene

    def importDSA(self, path: str, title: str, ctaNode=None, **overrides):
        """Read a DSA run (DICOM XA, or NIfTI + JSON sidecar) into a sequence node placed on
        its nominal detector plane (C-arm angles about the CTA grid centre)."""
        from geopose import mrml
        from geopose.dsa import read_dsa
        from geopose.geometry.poses import pose_from_carm_angles

        run = read_dsa(path, **overrides)
        pose = pose_from_carm_angles(run.angles)
        if ctaNode is not None:
            pose = mrml.volume_from_node(ctaNode).centred_to_ras @ pose
        frameTime = run.frame_time_ms / 1000.0 if run.frame_time_ms else None
        return mrml.dsa_sequence_node(
            self._scene(), run.frames, run.detector, pose, f"DSA {title}", frame_time_s=frameTime, angles=run.angles
        )

    def dsaRunFromNode(self, node, overrides: Optional[dict] = None):
        """A ``geopose.dsa.DSARun`` from a sequence / multi-frame volume node, its ``GeoPose.*``
        geometry attributes and ``overrides`` (``geopose.dsa`` key names, mm / deg)."""
        from geopose import mrml
        from geopose.dsa import DSAInputError, DSARun
        from geopose.geometry import CArmAngles, Detector

        overrides = dict(overrides or {})
        frames = mrml.frames_from_node(node)
        detector, angles, frameTime = mrml.geometry_from_attributes(node)
        geo = {}
        if detector is not None:
            geo.update(sid_mm=detector.sdd_mm, pixel_spacing_mm=detector.spacing_mm,
                       principal_offset_mm=detector.principal_offset_mm)
        if angles is not None:
            geo.update(primary_deg=angles.primary_deg, secondary_deg=angles.secondary_deg,
                       sid_mm=angles.sid_mm, sod_mm=angles.sod_mm)
        geo.update(overrides)
        missing = [k for k in OVERRIDE_KEYS if k not in geo]
        if missing:
            raise DSAInputError(
                f"DSA node {node.GetName()!r} has no {', '.join(missing)}: import it with 'Import DSA...' "
                "or enter the values under 'Geometry overrides'"
            )
        det = Detector(frames.shape[1], frames.shape[2], tuple(geo["pixel_spacing_mm"]), float(geo["sid_mm"]),
                       tuple(geo.get("principal_offset_mm", (0.0, 0.0))))
        ang = CArmAngles(float(geo["primary_deg"]), float(geo["secondary_deg"]), float(geo["sid_mm"]), float(geo["sod_mm"]))
        frameMs = geo.get("frame_time_ms", frameTime * 1000.0 if frameTime else None)
        return DSARun(frames, det, ang, frameMs, {"source": f"Slicer node {node.GetName()}"})

    # ------------------------------------------------------------ registration

    @staticmethod
    def defaultModelsFolder() -> Path:
        """Shipped models: ``Resources/Models`` beside this file (built) or at the repository root."""
        return resourceFile("Models")

    def register(
        self,
        cta,
        dsaPA,
        dsaLAT,
        segmentation=None,
        craniumMask=None,
        iterations: Optional[int] = None,
        refineSteps: Optional[int] = None,
        device: str = "auto",
        backend: str = "auto",
        models=None,
        overridesPA: Optional[dict] = None,
        overridesLAT: Optional[dict] = None,
        modelClipPercentiles: Optional[tuple] = None,
        progress: Optional[Callable[[str, float, str], None]] = None,
        cancel: Optional[Callable[[], bool]] = None,
    ) -> dict:
        """Register ``cta`` (scalar volume, HU) to the PA and lateral DSA runs (sequence or
        volume nodes). Input nodes are not modified. Returns the output nodes by name:
        ``{pa,lat}{Pose,Camera,Frustum,DSA,DSABrowser,MAP,Projection}``, ``table``, ``result``
        (the library's in-memory result) and ``record`` (the JSON-ready result record that
        ``geopose register`` writes as result.json). ``modelClipPercentiles`` (lo, hi): the
        clip of the networks' MAP (default CONVENTIONS 5, 25-75; see the README)."""
        if cta is None or dsaPA is None or dsaLAT is None:
            raise ValueError("register needs cta, dsaPA and dsaLAT nodes")
        from geopose import contract as C
        from geopose import mrml
        from geopose.options import RegistrationOptions
        from geopose.register.pipeline import register_case
        from geopose.register.record import build_record

        options = RegistrationOptions(
            backend=backend, device=device,
            refine_steps=C.GREEDY_MAX_PROPOSALS if refineSteps is None else refineSteps,
            iterations=C.TTO_ITERATIONS if iterations is None else iterations,
            model_clip_percentiles=modelClipPercentiles,
        )
        ctaVolume = mrml.volume_from_node(cta)
        runs = {"pa": self.dsaRunFromNode(dsaPA, overridesPA), "lat": self.dsaRunFromNode(dsaLAT, overridesLAT)}
        labels, segments = self.segmentationLabels(segmentation, cta)
        cranium = self.segmentationLabels(craniumMask, cta)[0] if craniumMask is not None else None
        result = register_case(
            ctaVolume, runs, models=models or self.defaultModelsFolder(), options=options, cranium_mask=cranium,
            segmentation=labels, progress=progress, cancel=cancel,
        )
        notes = result.notes
        for note in notes:
            logging.warning(note)
        outputs = self.addResultNodes(ctaVolume, runs, result, labels, segments, notes)
        outputs["result"] = result
        outputs["record"] = build_record(result, runs, inputs={"cta": {"node": cta.GetName()}})
        return outputs

    def segmentationLabels(self, segmentation, referenceNode):
        """``(label map Volume on the CTA grid, {value: (segment name, rgb)})``, or ``(None, {})``."""
        from geopose import mrml

        if segmentation is None:
            return None, {}
        labels, values = mrml.labelmap_from_segmentation(segmentation, referenceNode)
        colors = mrml.segment_colors(segmentation)
        return labels, {value: (name, colors[name]) for name, value in values.items()}

    def addResultNodes(self, ctaVolume, runs: dict, result, labels=None, segments=None, notes=()) -> dict:
        """Output nodes for a registration result. Consumes, per view key ``pa``/``lat``:
        ``result.views[key].final_pose`` (1x4x4 camera-to-centred, mm), ``.stage_poses``,
        ``.final_mncc``, ``.silhouette_dice``, ``.quality.flag`` / ``.quality.reasons``,
        ``.prepared.map`` (native MAP); and ``result.runtimes_s``, ``result.device``."""
        from geopose import mrml

        scene = self._scene()
        out: dict = {}
        rows = []
        for key in VIEW_KEYS:
            view, run, title = result.views[key], runs[key], VIEW_TITLES[key]
            poseCentred = _matrix(view.final_pose)
            poseRas = ctaVolume.centred_to_ras @ poseCentred
            out[f"{key}Pose"] = mrml.pose_transform_node(scene, poseRas, f"GeoPose {title} pose")
            out[f"{key}Camera"] = mrml.camera_node(scene, poseRas, run.detector, f"GeoPose {title} camera")
            out[f"{key}Frustum"] = mrml.frustum_model_node(scene, poseRas, run.detector, f"GeoPose {title} C-arm")
            frameTime = run.frame_time_ms / 1000.0 if run.frame_time_ms else None
            out[f"{key}DSA"], out[f"{key}DSABrowser"] = mrml.dsa_sequence_node(
                scene, run.frames, run.detector, poseRas, f"GeoPose {title} DSA", frame_time_s=frameTime, angles=run.angles
            )
            out[f"{key}MAP"] = mrml.plane_volume_node(scene, view.prepared.map, run.detector, poseRas, f"GeoPose {title} MAP")
            mrml.set_geometry_attributes(out[f"{key}MAP"], run.detector, run.angles, frameTime)
            if labels is not None and segments:
                out[f"{key}Projection"] = mrml.projected_segmentation_node(
                    scene, labels, segments, poseCentred, run.detector, f"GeoPose {title} projected segmentation"
                )
            row = {"view": title, "mNCC": float(view.final_mncc), "silhouette Dice": float(view.silhouette_dice),
                   "quality": view.quality.flag, "reasons": "; ".join(view.quality.reasons)}
            for stage, pose in view.stage_poses.items():
                moved = _matrix(pose)[:3, 3] - poseCentred[:3, 3]
                row[f"{stage} to final (mm)"] = float(math.sqrt((moved ** 2).sum()))
            rows.append(row)
        for row in rows:
            row.update({f"runtime {stage} (s)": float(t) for stage, t in result.runtimes_s.items()})
            row["device"] = f"{result.engine['backend']} on {result.engine['device']}"
            row["notes"] = "; ".join(notes)
        out["table"] = mrml.result_table_node(scene, rows, "GeoPose results")
        return out

    @staticmethod
    def summary(outputs: dict) -> str:
        """One line per view: mNCC and quality flag (from the result table)."""
        table = outputs.get("table")
        if table is None:
            return ""
        cols = {table.GetColumnName(c): c for c in range(table.GetNumberOfColumns())}
        lines = []
        for r in range(table.GetNumberOfRows()):
            lines.append(
                f"{table.GetCellText(r, cols['view'])}: mNCC {float(table.GetCellText(r, cols['mNCC'])):.3f}, "
                f"{table.GetCellText(r, cols['quality'])}"
            )
        return "\n".join(lines)

    @staticmethod
    def planeAxes(planeNode):
        """(normal, column direction, centre) of a detector-plane volume node, RAS."""
        from geopose import mrml

        vol = mrml.volume_from_node(planeNode)
        m = vol.ijk_to_ras
        i, j, _k = vol.shape_ijk
        centre = m @ [(i - 1) / 2, (j - 1) / 2, 0, 1]
        unit = lambda v: v / max(float((v ** 2).sum()) ** 0.5, 1e-12)  # noqa: E731
        return unit(m[:3, 2]), unit(m[:3, 0]), centre[:3]


def _matrix(pose):
    """A (1,4,4) / (4,4) torch tensor or array -> 4x4 float64 numpy."""
    import numpy as np

    value = pose.detach().cpu().numpy() if hasattr(pose, "detach") else np.asarray(pose)
    return np.asarray(value, dtype=float).reshape(4, 4)


#
# GeoPoseTest
#


class GeoPoseTest(ScriptedLoadableModuleTest):
    """Runs the whole registration on a phantom case inside Slicer."""

    def setUp(self) -> None:
        slicer.mrmlScene.Clear()

    def runTest(self) -> None:
        self.setUp()
        self.test_GeoPosePhantom()

    def test_GeoPosePhantom(self) -> None:
        import tempfile

        import numpy as np
        from geopose import mrml
        from geopose.cli import main as geoposeMain

        if not GeoPoseLogic.torchAvailable():
            self.delayDisplay("Skipped: simulating the phantom case needs PyTorch (install the PyTorch extension)")
            return
        self.delayDisplay("Generating a phantom case")
        folder = Path(tempfile.mkdtemp(prefix="geopose-test-"))
        self.assertEqual(geoposeMain(["phantom", "--seed", "0", "--out", str(folder)]), 0)
        scene = slicer.mrmlScene
        cta = mrml.read_volume_node(scene, folder / "cta.nii.gz", "CTA")
        labels = mrml.volume_from_node(mrml.read_volume_node(scene, folder / "labels.nii.gz", "labels", labelmap=True))
        vessels = mrml.segmentation_from_labelmap(scene, labels.like((labels.array > 0).astype(np.uint8)),
                                                  {1: ("vessels", (0.9, 0.2, 0.2))}, "Vessels")
        logic = GeoPoseLogic()
        pa, _b = logic.importDSA(str(folder / "dsa_pa.dcm"), "PA", ctaNode=cta)
        lat, _b = logic.importDSA(str(folder / "dsa_lat.dcm"), "LAT", ctaNode=cta)
        before = mrml.volume_from_node(cta).array.copy()
        self.delayDisplay("Registering")
        out = logic.register(cta=cta, dsaPA=pa, dsaLAT=lat, segmentation=vessels)
        np.testing.assert_array_equal(mrml.volume_from_node(cta).array, before)
        for key in VIEW_KEYS:
            self.assertIsNotNone(out[f"{key}Pose"])
            self.assertGreater(float(out["result"].views[key].final_mncc), 0.0)
        self.delayDisplay("Test passed")
