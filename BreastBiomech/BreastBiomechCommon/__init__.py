"""Helpers shared by the BreastBiomech scripted modules (not a module itself: Slicer only loads
the ``*.py`` files directly in this folder as modules).

- the Slicer framework base classes, or a stand-in where only the ``slicer-core`` wheel is present
  (headless: Logic classes work; Module, Widget and Test classes refuse to be instantiated);
- finding ``BreastBiomechLib`` and the shared ``Resources/`` both in a built extension (copied
  beside the module scripts) and in a source checkout (one folder up);
- installing missing Python dependencies on first use, after asking the user;
- the parameter-node lifecycle shared by the module Widgets, and the Logic base that owns the
  scene and the module's parameter node.
"""

from __future__ import annotations

import importlib.util
import os
import sys

_HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the module scripts' folder
_SOURCE_ROOT = os.path.dirname(_HERE)                                 # a source checkout's root

try:  # inside the Slicer application
    from slicer.ScriptedLoadableModule import (  # noqa: F401
        ScriptedLoadableModule,
        ScriptedLoadableModuleTest,
        ScriptedLoadableModuleWidget,
    )

    IN_SLICER_APPLICATION = True
except ImportError:  # the slicer-core wheel: MRML and module logic only, no application or Qt

    class _ApplicationOnly:
        """Headless stand-in for the application's Module/Widget/Test base classes: those classes
        can be defined (so the module file imports) but are never instantiated headless."""

        def __init__(self, *args, **kwargs):
            raise RuntimeError("this class needs the Slicer application; headless, use the Logic class")

    ScriptedLoadableModule = ScriptedLoadableModuleWidget = ScriptedLoadableModuleTest = _ApplicationOnly
    IN_SLICER_APPLICATION = False

class ParameterNodeWidgetMixin:
    """The parameter-node lifecycle every module Widget shares (Slicer's scripted-module template):
    observe the Logic's parameter node while the module is shown, drop it on scene close, and
    refresh the panel through ``updateGUIFromParameterNode``. Mix in before
    ``VTKObservationMixin``; the Widget sets ``self.logic`` and ``self._parameterNode = None``."""

    def cleanup(self):
        self.removeObservers()

    def enter(self):
        self.initializeParameterNode()

    def exit(self):
        self._setParameterNode(None)

    def onSceneStartClose(self, caller, event):
        self._setParameterNode(None)

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self):
        self._setParameterNode(self.logic.getParameterNode())

    def _setParameterNode(self, parameterNode):
        import vtk

        if self._parameterNode is not None:
            self.removeObserver(self._parameterNode.node, vtk.vtkCommand.ModifiedEvent, self.updateGUIFromParameterNode)
        self._parameterNode = parameterNode
        if parameterNode is not None:
            self.addObserver(parameterNode.node, vtk.vtkCommand.ModifiedEvent, self.updateGUIFromParameterNode)
        self.updateGUIFromParameterNode()


class ParameterNodeLogic:
    """Base of the module Logics: holds the scene (``slicer.mrmlScene`` by default) and gives the
    module's parameter node. Subclasses set ``MODULE_NAME``, ``DEFAULTS`` (names -> default
    values, whose types the values keep) and ``ROLES`` (node-reference names)."""

    MODULE_NAME = ""
    DEFAULTS: dict = {}
    ROLES: tuple = ()

    def __init__(self, scene=None):
        if scene is None:
            import slicer

            scene = slicer.mrmlScene
        self.scene = scene

    def getParameterNode(self):
        from BreastBiomechLib.mrml import ParameterNode

        return ParameterNode(self.scene, self.MODULE_NAME, self.DEFAULTS, self.ROLES)


# Python packages the library needs that a Slicer installation may lack: import name -> pip name
DEPENDENCIES = {"scipy": "scipy", "SimpleITK": "SimpleITK", "matplotlib": "matplotlib",
                "tetgen": "tetgen", "warp": "warp-lang", "cma": "cma"}


def resolve_device(choice: str) -> str:
    """The warp device for a panel's choice: "cuda" or "cpu" for "auto" (the GPU when present),
    "cuda" (refused without a GPU) or "cpu"."""
    import warp as wp

    if choice not in ("auto", "cuda", "cpu"):
        raise ValueError(f"device must be auto, cuda or cpu, not {choice!r}")
    wp.init()
    cuda = wp.get_cuda_device_count() > 0
    if choice == "cuda" and not cuda:
        raise ValueError("no CUDA GPU was found; choose the device 'auto' or 'cpu'")
    return ("cuda" if cuda else "cpu") if choice == "auto" else choice


def ensure_library_importable() -> None:
    """Make ``import BreastBiomechLib`` work when the modules run from a source checkout."""
    if importlib.util.find_spec("BreastBiomechLib") is None and os.path.isdir(
            os.path.join(_SOURCE_ROOT, "BreastBiomechLib")):
        sys.path.insert(0, _SOURCE_ROOT)


def resource_path(relative: str) -> str:
    """Absolute path of a shared resource, e.g. ``resource_path("UI/BreastBiomech.ui")``."""
    for root in (_HERE, _SOURCE_ROOT):
        candidate = os.path.join(root, "Resources", relative)
        if os.path.exists(candidate):
            return candidate
    raise FileNotFoundError(f"BreastBiomech resource {relative!r} not found beside {_HERE} or in {_SOURCE_ROOT}")


def missing_dependencies(names) -> list[str]:
    """pip names of the dependencies among ``names`` (import names) that cannot be imported."""
    return [DEPENDENCIES[n] for n in names if importlib.util.find_spec(n) is None]


def ensure_dependencies(names) -> bool:
    """Inside Slicer: offer to pip-install what is missing; True when everything is importable."""
    missing = missing_dependencies(names)
    if not missing:
        return True
    if not IN_SLICER_APPLICATION:
        raise ImportError(f"missing Python packages {missing}: pip install {' '.join(missing)}")
    import slicer

    if not slicer.util.confirmOkCancelDisplay(
            f"BreastBiomech needs these Python packages: {', '.join(missing)}.\n"
            "Install them now into Slicer's Python (this downloads them)?",
            "BreastBiomech dependencies"):
        return False
    slicer.util.pip_install(" ".join(missing))
    importlib.invalidate_caches()
    return not missing_dependencies(names)
