"""TEST-ONLY stand-in for Slicer's scripted-module base classes (no Qt); see ../README.md."""

from __future__ import annotations

import unittest

import slicer

__all__ = ["ScriptedLoadableModule", "ScriptedLoadableModuleWidget", "ScriptedLoadableModuleLogic", "ScriptedLoadableModuleTest"]


class ScriptedLoadableModule:
    def __init__(self, parent=None):
        self.parent = parent


class ScriptedLoadableModuleWidget:
    def __init__(self, parent=None):
        raise RuntimeError("the module widget needs the Slicer application (Qt); the stand-ins cover the logic only")


class ScriptedLoadableModuleLogic:
    """Keeps one parameter node per logic in ``slicer.mrmlScene`` (set by the test)."""

    def __init__(self, parent=None):
        self._parameterNode = None

    def getParameterNode(self):
        if self._parameterNode is None:
            self._parameterNode = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", type(self).__name__)
        return self._parameterNode


class ScriptedLoadableModuleTest(unittest.TestCase):
    pass
