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

    class qMRMLSortFilterProxyModel:
        """The filter of a node combo box: ``hiddenNodeIDs`` (what Slicer's qMRMLSortFilterProxyModel
        rejects first); setting it refilters the combo box."""

        def __init__(self, combo) -> None:
            self._combo = combo
            self._hidden: list = []

        @property
        def hiddenNodeIDs(self) -> list:
            return list(self._hidden)

        @hiddenNodeIDs.setter
        def hiddenNodeIDs(self, ids) -> None:
            self._hidden = list(ids)
            self._combo._refilter()

    class qMRMLNodeComboBox(qMRMLWidget):
        """The node list and selection of Slicer's combo box, as its C++ filters them
        (qMRMLSortFilterProxyModel::filterAcceptsNode: hidden node IDs, HideFromEditors, node types,
        child types), with its automatic selection: without a "None" entry the first node listed is
        selected when there is none, and a selected node that stops being listed is replaced (by
        the first node listed, or None). No "create new" entry and no attribute filters."""

        _signals = ("currentNodeChanged", "currentNodeIDChanged")

        def __init__(self, parent=None) -> None:
            super().__init__(parent)
            self.nodeTypes, self.noneEnabled, self.addEnabled, self.removeEnabled = [], False, False, False
            self.showChildNodeTypes, self.renameEnabled, self.noneDisplay = True, False, ""
            self._node = None
            self._filter = qMRMLSortFilterProxyModel(self)
            self._observed = []

        def sortFilterProxyModel(self):
            return self._filter

        def setMRMLScene(self, scene) -> None:
            for observed, tag in self._observed:
                observed.RemoveObserver(tag)
            self._observed = [(scene, scene.AddObserver(event, lambda *args: self._refilter()))
                              for event in (scene.NodeAddedEvent, scene.NodeRemovedEvent)] if scene is not None else []
            super().setMRMLScene(scene)
            self._refilter()

        def _accepts(self, node) -> bool:
            if node.GetID() in self._filter.hiddenNodeIDs or node.GetHideFromEditors():
                return False
            if self.showChildNodeTypes:
                return any(node.IsA(t) for t in self.nodeTypes)
            return node.GetClassName() in self.nodeTypes

        def nodes(self) -> list:
            """The nodes the combo box lists, in scene order."""
            scene = self.mrmlScene()
            if scene is None:
                return []
            found = [scene.GetNthNode(n) for n in range(scene.GetNumberOfNodes())]
            return [node for node in found if self._accepts(node)]

        def _refilter(self) -> None:
            listed = self.nodes()
            if self._node is not None and not any(node is self._node for node in listed):
                self.setCurrentNode(None if self.noneEnabled or not listed else listed[0])
            elif self._node is None and not self.noneEnabled and listed:
                self.setCurrentNode(listed[0])

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
    """``slicer.app``: the version, testing mode, translation (none), no main window, and an event
    queue: :meth:`post` queues what a user does (a click, an edit) and :meth:`processEvents` runs
    what is queued, as Qt's event loop does, recording when it was called (``processEventsTimes``,
    ``time.perf_counter`` s)."""

    applicationName = "Slicer"

    def __init__(self, tag: str, testing: bool = True) -> None:
        self.majorVersion, self.minorVersion, self.patchVersion = (int(v) for v in tag.lstrip("v").split("."))
        self.testing = testing
        self._events: list = []
        self.processEventsTimes: list = []

    def post(self, event) -> None:
        """Queue ``event()`` (a user action) for the next :meth:`processEvents`."""
        self._events.append(event)

    def testingEnabled(self) -> bool:
        return self.testing

    def translate(self, context: str, text: str) -> str:
        return text

    def moduleManager(self) -> _ModuleManager:
        return _ModuleManager()

    def topLevelWidgets(self) -> list:
        return []

    def processEvents(self) -> None:
        import time

        self.processEventsTimes.append(time.perf_counter())
        events, self._events = self._events, []
        for event in events:
            event()

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
        if name in ("GeoPose", "GeoPoseTest") or any(name == m or name.startswith(m + ".") for m in _SLICER_LAYER):
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
    import qt

    qt.QSettings.store.clear()  # a fresh application's settings
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
        widget = _WIDGETS.pop()
        widget.cleanup()
        for combo in widget.parent.findChildren(slicer.qMRMLNodeComboBox):
            combo.setMRMLScene(None)  # its scene observers go with it
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
