"""Scene set-up, 4x4 matrix conversion and ``.mrb`` bundles.

Inside 3D Slicer the application has already registered segmentation
converters, default colour tables and I/O managers; in plain Python
(``slicer-core``) :func:`prepare_scene` adds what the adapters need.
"""

from __future__ import annotations

import tempfile
import weakref
from pathlib import Path

import numpy as np
import slicer
import vtk

from ..errors import InputError

__all__ = [
    "new_scene", "prepare_scene", "sequences_logic", "matrix_to_vtk", "matrix_from_vtk", "save_mrb", "load_mrb", "output_node",
]

#: Colour table that label-map display nodes look up by default.
_LABELS_COLOR_NODE_ID = "vtkMRMLColorTableNodeLabels"
#: Scratch folder the scene's cache manager uses when reading bundles outside Slicer.
_CACHE_DIR = Path(tempfile.gettempdir()) / "geopose-mrml-cache"
#: One Sequences logic per scene outside the Slicer application (binding it registers node classes).
_SEQUENCES_LOGICS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _register_segmentation_converters() -> None:
    factory = slicer.vtkSegmentationConverterFactory.GetInstance()
    have = {type(factory.GetConverterRules()[i]).__name__ for i in range(len(factory.GetConverterRules()))}
    for rule in (slicer.vtkBinaryLabelmapToClosedSurfaceConversionRule, slicer.vtkClosedSurfaceToBinaryLabelmapConversionRule):
        if rule.__name__ not in have:
            factory.RegisterConverterRule(rule())


def sequences_logic(scene: "slicer.vtkMRMLScene"):
    """Slicer's Sequences module logic, or one bound to ``scene`` outside the application."""
    modules = getattr(slicer, "modules", None)
    if modules is not None and hasattr(modules, "sequences"):
        return modules.sequences.logic()
    logic = _SEQUENCES_LOGICS.get(scene)
    if logic is None:
        logic = slicer.vtkSlicerSequencesLogic()
        logic.SetMRMLScene(scene)
        _SEQUENCES_LOGICS[scene] = logic
    return logic


def prepare_scene(scene: "slicer.vtkMRMLScene") -> "slicer.vtkMRMLScene":
    """Make ``scene`` usable by the adapters outside the Slicer application (idempotent)."""
    _register_segmentation_converters()
    sequences_logic(scene)  # registers the sequence node classes outside Slicer
    if scene.GetCacheManager() is None:
        cache = slicer.vtkCacheManager()
        _CACHE_DIR.mkdir(parents=True, exist_ok=True)
        cache.SetRemoteCacheDirectory(str(_CACHE_DIR))
        scene.SetCacheManager(cache)
    if scene.GetDataIOManager() is None:
        io = slicer.vtkDataIOManager()
        io.SetCacheManager(scene.GetCacheManager())
        scene.SetDataIOManager(io)
    if scene.GetNodeByID(_LABELS_COLOR_NODE_ID) is None:
        colors = slicer.vtkMRMLColorLogic()
        colors.SetMRMLScene(scene)  # adds the default colour tables
        colors.SetMRMLScene(None)
    return scene


def new_scene() -> "slicer.vtkMRMLScene":
    """An empty scene prepared with :func:`prepare_scene`."""
    return prepare_scene(slicer.vtkMRMLScene())


def output_node(scene: "slicer.vtkMRMLScene", class_name: str, name: str, node=None):
    """The node an output goes into: ``node`` when given (chosen by the user or made by an
    earlier run; it is updated in place and keeps its name), else a new ``class_name`` node ``name``."""
    if node is None:
        return scene.AddNewNodeByClass(class_name, name)
    if not node.IsA(class_name):
        raise InputError(f"output node {node.GetName()!r} is a {node.GetClassName()}, not a {class_name}: choose another output node")
    return node


def matrix_to_vtk(m: np.ndarray) -> vtk.vtkMatrix4x4:
    """4x4 numpy -> ``vtkMatrix4x4``."""
    m = np.asarray(m, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"expected a finite 4x4 matrix, got shape {m.shape}")
    out = vtk.vtkMatrix4x4()
    out.DeepCopy(m.ravel().tolist())
    return out


def matrix_from_vtk(m: vtk.vtkMatrix4x4) -> np.ndarray:
    """``vtkMatrix4x4`` -> 4x4 numpy."""
    return np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)])


def save_mrb(scene: "slicer.vtkMRMLScene", path: str | Path) -> Path:
    """Write the whole scene with its data as one Medical Reality Bundle."""
    path = Path(path)
    if path.suffix.lower() != ".mrb":
        raise ValueError(f"a scene bundle is saved as .mrb, got {path.name!r}: use a name ending in .mrb")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not scene.WriteToMRB(str(path)):
        raise OSError(f"could not write the scene bundle {path}: check the folder is writable")
    return path


def load_mrb(path: str | Path) -> "slicer.vtkMRMLScene":
    """Read a ``.mrb`` bundle into a new prepared scene."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene bundle not found: {path}")
    scene = new_scene()
    if not scene.ReadFromMRB(str(path)):
        raise OSError(f"could not read the scene bundle {path}: is it a valid .mrb written by Slicer?")
    return scene
