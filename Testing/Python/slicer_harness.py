"""Run ``GeoPoseModule/GeoPose.py`` on Slicer's real Python layer without the Slicer application.

``shared/slicer-api/<tag>/slicer/`` holds Slicer's unmodified ``ScriptedLoadableModule``,
``i18n``, ``parameterNodeWrapper`` (and, from 5.12, ``packaging``); :func:`load_module` puts
that folder ahead on ``slicer.__path__`` (the ``slicer-core`` wheel provides MRML and
``slicer.util``), adds the minimal ``qt``/``ctk`` stand-ins of ``Testing/QtStandIns`` and the
few application-level objects those files reach (``slicer.app`` and Slicer's Qt widget
classes ``qMRMLWidget``, ``qMRMLNodeComboBox``, ``qMRMLTableView``), then imports the module
file fresh. :func:`unload` undoes all of it. Both the in-process tests and subprocess
scripts (``python -c``) use it.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from shared_folder import find_shared

REPO = Path(__file__).resolve().parents[2]
QT_STAND_INS = REPO / "Testing" / "QtStandIns"
MODULE_FILE = REPO / "GeoPoseModule" / "GeoPose.py"
UI_FILE = REPO / "Resources" / "UI" / "GeoPose.ui"
#: Slicer release tags whose Python layer is in ``shared/slicer-api``.
SLICER_TAGS = ("v5.8.1", "v5.12.3")
#: Modules of Slicer's Python layer that :func:`load_module` swaps per tag.
_SLICER_LAYER = ("slicer.ScriptedLoadableModule", "slicer.i18n", "slicer.parameterNodeWrapper", "slicer.packaging")
#: Widgets made by :func:`new_widget`; :func:`unload` cleans them up as Slicer does when unloading a module.
_WIDGETS: list = []
#: Application-level names :func:`load_module` sets on ``slicer``.
_APP_NAMES = ("app", "selfTests", "qMRMLWidget", "qMRMLNodeComboBox", "qMRMLTableView", "qMRMLSliderWidget",
              "qMRMLSpinBox", "qMRMLRangeWidget")


def slicer_api() -> Path:
    """``shared/slicer-api`` (:func:`shared_folder.find_shared`, as every test finds ``shared/``)."""
    return find_shared() / "slicer-api"


def _stand_in_classes():
    """Slicer's Qt widget classes (``slicer.qMRML*``), as thin ``qt`` stand-in subclasses."""
    import ctk
    import qt

    class qMRMLWidget(qt.QWidget):
        _signals = ("mrmlSceneChanged",)

        def __init__(self, parent=None) -> None:
            super().__init__(parent)
            self._scene = None

        def setMRMLScene(self, scene) -> None:
            self._scene = scene
            self.mrmlSceneChanged.emit(scene)

        def mrmlScene(self):
            return self._scene

    class qMRMLNodeComboBox(qMRMLWidget):
        """The node selection only (no automatic selection, no "create new" entry: those are C++)."""

        _signals = ("currentNodeChanged", "currentNodeIDChanged")

        def __init__(self, parent=None) -> None:
            super().__init__(parent)
            self.nodeTypes, self.noneEnabled, self.addEnabled, self.removeEnabled = [], False, False, False
            self.showChildNodeTypes, self.renameEnabled, self.noneDisplay = True, False, ""
            self._node = None

        def currentNode(self):
            return self._node

        def setCurrentNode(self, node) -> None:
            if node is not self._node:
                self._node = node
                self.currentNodeChanged.emit(node)
                self.currentNodeIDChanged.emit(node.GetID() if node is not None else "")

    class qMRMLTableView(qt.QTableView):
        def __init__(self, parent=None) -> None:
            super().__init__(parent)
            self._table = None

        def setMRMLScene(self, scene) -> None:
            pass

        def setMRMLTableNode(self, node) -> None:
            self._table = node

        def mrmlTableNode(self):
            return self._table

    class qMRMLSliderWidget(ctk.ctkSliderWidget):
        pass

    class qMRMLSpinBox(ctk.ctkDoubleSpinBox):
        pass

    class qMRMLRangeWidget(ctk.ctkRangeWidget):
        pass

    return {c.__name__: c for c in (qMRMLWidget, qMRMLNodeComboBox, qMRMLTableView, qMRMLSliderWidget, qMRMLSpinBox, qMRMLRangeWidget)}


class _ModuleManager:
    def connect(self, signal: str, slot) -> None:
        pass

    def disconnect(self, signal: str, slot) -> None:
        pass


class StandInApp:
    """``slicer.app``: the version, testing mode, translation (none) and no main window."""

    applicationName = "Slicer"

    def __init__(self, tag: str, testing: bool = True) -> None:
        self.majorVersion, self.minorVersion, self.patchVersion = (int(v) for v in tag.lstrip("v").split("."))
        self.testing = testing

    def testingEnabled(self) -> bool:
        return self.testing

    def translate(self, context: str, text: str) -> str:
        return text

    def moduleManager(self) -> _ModuleManager:
        return _ModuleManager()

    def topLevelWidgets(self) -> list:
        return []

    def processEvents(self) -> None:
        pass

    def setOverrideCursor(self, cursor) -> None:
        pass

    def restoreOverrideCursor(self) -> None:
        pass

    def thread(self):
        import qt

        return qt.QThread.currentThread()

    def layoutManager(self):
        return None


def _purge() -> None:
    import slicer

    for name in list(sys.modules):
        if name == "GeoPose" or any(name == m or name.startswith(m + ".") for m in _SLICER_LAYER):
            del sys.modules[name]
    for attr in ("ScriptedLoadableModule", "i18n", "parameterNodeWrapper", "packaging", *_APP_NAMES):
        if attr in vars(slicer):
            delattr(slicer, attr)


def load_module(tag: str, scene, testing: bool = True, path: Path = MODULE_FILE):
    """Import ``GeoPose.py`` (``path``) against ``shared/slicer-api/<tag>`` with ``slicer.mrmlScene = scene``."""
    import slicer

    layer = slicer_api() / tag / "slicer"
    if not layer.is_dir():
        raise FileNotFoundError(f"Slicer's Python layer {layer} is missing (shared/slicer-api)")
    if str(QT_STAND_INS) not in sys.path:
        sys.path.insert(0, str(QT_STAND_INS))
    _purge()
    wheel = [p for p in slicer.__path__ if not p.startswith(str(slicer_api()))]
    slicer.__path__[:] = [str(layer), *wheel]
    for name, cls in _stand_in_classes().items():
        setattr(slicer, name, cls)
    slicer.app = StandInApp(tag, testing)
    slicer.mrmlScene = scene
    spec = importlib.util.spec_from_file_location("GeoPose", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["GeoPose"] = module  # ScriptedLoadableModule.runTest imports the module by name
    spec.loader.exec_module(module)
    return module


def unload() -> None:
    """Remove what :func:`load_module` added (the wheel's ``slicer`` is left as it was)."""
    import slicer

    while _WIDGETS:
        _WIDGETS.pop().cleanup()
    _purge()
    slicer.__path__[:] = [p for p in slicer.__path__ if not p.startswith(str(slicer_api()))]
    if "mrmlScene" in vars(slicer):
        del slicer.mrmlScene


def load_ui():
    """The panel built from ``Resources/UI/GeoPose.ui`` (stand-in widgets keyed by objectName)."""
    import slicer

    return slicer.util.loadUI(str(UI_FILE))


def new_widget(module):
    """``GeoPoseWidget`` in a parent panel, after ``setup()``, as Slicer's module panel creates it."""
    import qt
    import slicer

    parent = slicer.qMRMLWidget()
    parent.setLayout(qt.QVBoxLayout())
    widget = module.GeoPoseWidget(parent)
    widget.setup()
    parent.isEntered = True
    _WIDGETS.append(widget)
    return widget
