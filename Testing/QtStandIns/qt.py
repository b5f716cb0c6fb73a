"""TEST-ONLY, MINIMAL stand-in for PythonQt's ``qt`` module (no Qt is installed here).

It holds only what Slicer's real Python layer (``../shared/slicer-api/<tag>/slicer/``:
``ScriptedLoadableModule``, ``parameterNodeWrapper`` and its GUI connectors, ``i18n``,
``packaging``), the ``slicer-core`` wheel's ``slicer.util`` (``loadUI``,
``childWidgetVariables``, message boxes) and ``GeoPoseModule/GeoPose.py`` touch:

- ``QObject``/``QWidget``: object name, parent/children, dynamic properties
  (``property``/``setProperty``), PythonQt-style attributes (``enabled``, ``toolTip``,
  ``text``, ``value``...), ``connect("signal(args)", slot)`` and signal objects;
- the value widgets the GUI connectors drive (check box, push button, spin boxes,
  combo box, label...): setting the value emits the change signal, as in Qt;
- ``QUiLoader``: builds a tree of these widgets from a Designer ``.ui`` file (classes by
  name from ``qt``, ``ctk`` and ``slicer``; properties; combo items; the file's
  signal/slot connections), keyed by ``objectName`` as Qt's loader does.

Not covered, because it needs a real Qt: painting, layout geometry, focus and
keyboard, event loops, dialogs (file dialogs and message boxes are answered by the
test), and the behaviour of Slicer's C++ widgets beyond their Python properties.
"""

from __future__ import annotations

import inspect
import xml.etree.ElementTree as ET
from pathlib import Path


class Signal:
    """A Qt signal: ``connect(slot)``, ``disconnect(slot)``, ``emit(*args)``."""

    def __init__(self) -> None:
        self._slots: list = []

    def connect(self, slot) -> None:
        self._slots.append(slot)

    def disconnect(self, slot=None) -> None:
        if slot is None:
            self._slots.clear()
        elif slot in self._slots:
            self._slots.remove(slot)

    def emit(self, *args) -> None:
        for slot in list(self._slots):
            _call(slot, args)


def _call(slot, args: tuple) -> None:
    """Call ``slot`` with as many of ``args`` as it takes, as PythonQt does."""
    try:
        params = list(inspect.signature(slot).parameters.values())
    except (TypeError, ValueError):
        slot(*args)
        return
    if any(p.kind == p.VAR_POSITIONAL for p in params):
        slot(*args)
        return
    slot(*args[:sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params)])


class QObject:
    """Object name, parent/children, dynamic properties and PythonQt's ``connect``."""

    _signals: tuple[str, ...] = ()

    def __init__(self, parent: "QObject | None" = None) -> None:
        self.objectName = ""
        self._parent = None
        self._children: list[QObject] = []
        self._properties: dict[str, object] = {}
        for name in self._all_signals():
            setattr(self, name, Signal())
        if parent is not None:
            self.setParent(parent)

    @classmethod
    def _all_signals(cls) -> list[str]:
        return [s for klass in reversed(cls.__mro__) for s in getattr(klass, "_signals", ())]

    # PythonQt exposes objectName as ``name`` too.
    @property
    def name(self) -> str:
        return self.objectName

    @name.setter
    def name(self, value: str) -> None:
        self.objectName = value

    def setObjectName(self, value: str) -> None:
        self.objectName = value

    def parent(self) -> "QObject | None":
        return self._parent

    def setParent(self, parent: "QObject | None") -> None:
        if self._parent is not None:
            self._parent._children.remove(self)
        self._parent = parent
        if parent is not None:
            parent._children.append(self)

    def children(self) -> list["QObject"]:
        return list(self._children)

    def findChildren(self, cls=None) -> list["QObject"]:
        found = []
        for child in self._children:
            if cls is None or isinstance(child, cls):
                found.append(child)
            found += child.findChildren(cls)
        return found

    def property(self, name: str):
        return self._properties.get(name)

    def setProperty(self, name: str, value) -> None:
        self._properties[name] = value

    def connect(self, signature: str, slot) -> None:
        getattr(self, signature.split("(")[0]).connect(slot)

    def disconnect(self, signature: str, slot=None) -> None:
        getattr(self, signature.split("(")[0]).disconnect(slot)

    def isWidgetType(self) -> bool:
        return False

    def deleteLater(self) -> None:
        self.setParent(None)

    def className(self) -> str:
        return type(self).__name__


class QWidget(QObject):
    def __init__(self, parent: "QObject | None" = None) -> None:
        super().__init__(parent)
        self.enabled = True
        self.visible = True
        self.toolTip = ""
        self._layout = None

    def isWidgetType(self) -> bool:
        return True

    def isEnabled(self) -> bool:
        """Enabled, and so are all its parents (Qt disables the children of a disabled widget)."""
        parent = self.parent()
        return self.enabled and (parent is None or not isinstance(parent, QWidget) or parent.isEnabled())

    def show(self) -> None:
        self.visible = True

    def hide(self) -> None:
        self.visible = False

    def layout(self):
        return self._layout

    def setLayout(self, layout: "QLayout") -> None:
        self._layout = layout
        layout._owner = self


class QLayout(QObject):
    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__()
        self._owner = None
        if parent is not None:
            parent.setLayout(self)

    def addWidget(self, widget: QWidget, *args) -> None:
        widget.setParent(self._owner)

    def addRow(self, *items) -> None:
        for item in items:
            if isinstance(item, QWidget):
                self.addWidget(item)


class QVBoxLayout(QLayout):
    pass


class QHBoxLayout(QLayout):
    pass


class QFormLayout(QLayout):
    pass


class _Valued(QWidget):
    """A widget whose ``value``-like attribute emits a change signal when it changes."""

    _value_attribute = ""
    _change_signals: tuple[str, ...] = ()

    def __setattr__(self, key, value) -> None:
        if key == self._value_attribute and key in self.__dict__:
            changed = self.__dict__[key] != value
            super().__setattr__(key, value)
            if changed:
                for signal in self._change_signals:
                    getattr(self, signal).emit(value)
            return
        super().__setattr__(key, value)


class QLabel(QWidget):
    def __init__(self, text: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.text = text
        self.wordWrap = False


class QAbstractButton(_Valued):
    _signals = ("clicked", "toggled", "stateChanged")
    _value_attribute = "checked"
    _change_signals = ("toggled", "stateChanged")

    def __init__(self, text: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.text = text
        self.checkable = False
        self.checked = False

    def click(self) -> None:
        if not self.isEnabled():
            return
        if self.checkable:
            self.checked = not self.checked
        self.clicked.emit(self.checked)


class QPushButton(QAbstractButton):
    pass


class QToolButton(QAbstractButton):
    pass


class QCheckBox(QAbstractButton):
    def __init__(self, text: str = "", parent: QWidget | None = None) -> None:
        super().__init__(text, parent)
        self.checkable = True


class QSpinBox(_Valued):
    _signals = ("valueChanged",)
    _value_attribute = "value"
    _change_signals = ("valueChanged",)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.minimum, self.maximum, self.singleStep, self.suffix = 0, 99, 1, ""
        self.value = 0

    def setRange(self, minimum, maximum) -> None:
        self.minimum, self.maximum = minimum, maximum

    def setMinimum(self, minimum) -> None:
        self.minimum = minimum

    def setMaximum(self, maximum) -> None:
        self.maximum = maximum


class QDoubleSpinBox(QSpinBox):
    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.decimals = 2
        self.value = 0.0


class QSlider(QSpinBox):
    pass


class QComboBox(_Valued):
    _signals = ("currentIndexChanged",)
    _value_attribute = "currentIndex"
    _change_signals = ("currentIndexChanged",)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._items: list[str] = []
        self.currentIndex = -1

    def addItem(self, text: str) -> None:
        self._items.append(text)
        if self.currentIndex < 0:
            self.currentIndex = 0

    def clear(self) -> None:
        self._items = []
        self.currentIndex = -1

    def count(self) -> int:
        return len(self._items)

    def itemText(self, index: int) -> str:
        return self._items[index]

    @property
    def currentText(self) -> str:
        return self._items[self.currentIndex] if 0 <= self.currentIndex < len(self._items) else ""


class QLineEdit(_Valued):
    _signals = ("textChanged",)
    _value_attribute = "text"
    _change_signals = ("textChanged",)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.text = ""


class QTextEdit(QWidget):
    _signals = ("textChanged",)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._plain = ""

    def toPlainText(self) -> str:
        return self._plain

    def setPlainText(self, text: str) -> None:
        self._plain = text
        self.textChanged.emit()


class QProgressBar(QWidget):
    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.value = 0


class QTableView(QWidget):
    pass


class QIcon:
    def __init__(self, path: str = "") -> None:
        self.path = path


class QColor:
    def __init__(self, *args) -> None:
        self.args = args

    def name(self, *args) -> str:
        return str(self.args[0]) if self.args else "#000000"


class QSettings:
    """Application settings, kept in memory for the process (``QSettings.store``, which a test may clear)."""

    store: dict = {}

    def contains(self, key: str) -> bool:
        return key in QSettings.store

    def value(self, key: str, default=None):
        return QSettings.store.get(key, default)

    def setValue(self, key: str, value) -> None:
        QSettings.store[key] = value


class QThread:
    _current = object()

    @staticmethod
    def currentThread():
        return QThread._current


class QApplication:
    @staticmethod
    def processEvents() -> None:
        pass


class QMessageBox:
    Ok, Cancel, Yes, No, Retry, Close = 0x400, 0x400000, 0x4000, 0x10000, 0x80000, 0x200000
    Information, Warning, Critical, Question = 1, 2, 3, 4


class QFileDialog:
    """The test sets ``answer`` (the path a user would pick; "" = cancelled)."""

    answer = ""

    @staticmethod
    def getOpenFileName(*args) -> str:
        return QFileDialog.answer


class QFile:
    ReadOnly = 1

    def __init__(self, path: str) -> None:
        self.path = Path(str(path))

    def exists(self) -> bool:
        return self.path.is_file()

    def open(self, mode) -> bool:
        return self.exists()


# ------------------------------------------------------------------ .ui loader
def _widget_class(name: str):
    """The stand-in class of a Designer class name, from ``qt``, ``ctk`` or ``slicer``."""
    import ctk
    import slicer

    for namespace in (globals(), vars(ctk), vars(slicer)):
        cls = namespace.get(name)
        if isinstance(cls, type) and issubclass(cls, QWidget):
            return cls
    raise TypeError(f"no stand-in widget class {name!r}: add it to Testing/QtStandIns")


def _property_value(element: ET.Element):
    (value,) = list(element)
    if value.tag == "string":
        return value.text or ""
    if value.tag == "bool":
        return value.text == "true"
    if value.tag == "number":
        return int(value.text)
    if value.tag == "double":
        return float(value.text)
    if value.tag == "stringlist":
        return [s.text or "" for s in value]
    if value.tag == "enum":
        return value.text
    return None  # geometry (rect, size): layout only


class QUiLoader:
    """Builds the widget tree of a ``.ui`` file from the stand-in classes."""

    def load(self, qfile: QFile) -> QWidget:
        root = ET.parse(qfile.path).getroot()
        widgets: dict[str, QWidget] = {}
        top = self._build(root.find("widget"), None, widgets)
        for connection in root.iter("connection"):
            sender = widgets[connection.findtext("sender")]
            receiver = widgets[connection.findtext("receiver")]
            signal = connection.findtext("signal").split("(")[0]
            slot = connection.findtext("slot").split("(")[0]
            getattr(sender, signal).connect(getattr(receiver, slot))
        return top

    def _build(self, element: ET.Element, parent: QWidget | None, widgets: dict) -> QWidget:
        widget = _widget_class(element.get("class"))()
        widget.setParent(parent)
        widget.objectName = element.get("name")
        widgets[widget.objectName] = widget
        for prop in element.findall("property"):
            value = _property_value(prop)
            if value is None:
                continue
            if prop.get("stdset") == "0":
                widget.setProperty(prop.get("name"), value)
            else:
                setattr(widget, prop.get("name"), value)
        for item in element.findall("item"):  # combo box entries
            widget.addItem(_property_value(item.find("property")))
        for child in element:
            self._children(child, widget, widgets)
        return widget

    def _children(self, element: ET.Element, parent: QWidget, widgets: dict) -> None:
        if element.tag == "widget":
            self._build(element, parent, widgets)
        elif element.tag in ("layout", "item"):
            for child in element:
                self._children(child, parent, widgets)


class Qt:
    WaitCursor = 3
    ShiftModifier = 0x02000000
