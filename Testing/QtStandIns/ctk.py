"""TEST-ONLY, MINIMAL stand-in for CTK's Python module ``ctk`` (see ``qt.py`` beside it).

Slicer's GUI connectors compare widget types with these classes (``type(widget) in
(ctk.ctkSliderWidget, ...)``), so each exists as its own class; only
``ctkCollapsibleButton`` appears in ``Resources/UI/GeoPose.ui`` and has properties.
"""

from qt import QCheckBox, QComboBox, QDoubleSpinBox, QPushButton, QWidget


class ctkCollapsibleButton(QPushButton):
    def __init__(self, parent=None) -> None:
        super().__init__("", parent)
        self.collapsed = False


class ctkCheckBox(QCheckBox):
    pass


class ctkCheckablePushButton(QPushButton):
    pass


class ctkComboBox(QComboBox):
    pass


class ctkDoubleSpinBox(QDoubleSpinBox):
    pass


class ctkSliderWidget(QDoubleSpinBox):
    pass


class ctkDoubleSlider(QDoubleSpinBox):
    pass


class ctkRangeWidget(QWidget):
    pass


class ctkDoubleRangeSlider(QWidget):
    pass


class ctkPathLineEdit(QWidget):
    pass


class ctkDirectoryButton(QWidget):
    pass


class ctkColorPickerButton(QWidget):
    pass
