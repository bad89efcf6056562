"""Helpers shared by the BreastBiomech scripted modules (not a module itself: Slicer only loads
the ``*.py`` files directly in this folder as modules).

- the Slicer framework base classes, or a stand-in where only the ``slicer-core`` wheel is present
  (headless: Logic classes work; Module, Widget and Test classes refuse to be instantiated);
- Slicer's translation functions (``_``, ``translate``), identity functions headless;
- finding ``BreastBiomechLib`` (copied beside the module scripts in a built extension, one folder
  up in a source checkout) and the modules' ``Resources/`` (beside the module scripts in both);
- the parameter-node lifecycle shared by the module Widgets (their widgets bound to parameters by
  ``bindings``), the Logic base that owns the scene and the module's parameter node, and the
  self-test base that skips without its packages;
- (``dependencies``) checking and installing the Python packages on the first action that needs them.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import sys
import unittest

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

try:  # Slicer 5.4 and newer: strings shown to the user are translatable
    from slicer.i18n import tr as _  # noqa: F401
    from slicer.i18n import translate  # noqa: F401
except ImportError:  # the slicer-core wheel has no translations
    def _(text: str) -> str:
        return text

    def translate(context: str, text: str) -> str:
        return text

try:  # the application and the slicer-core wheel
    from slicer.util import VTKObservationMixin
except ImportError:  # no slicer package at all (the library tests on Slicer's own Python stack)

    class VTKObservationMixin:
        """Stand-in where only this package's dependency checks are used: the module Widgets,
        its only users, are never made without Slicer (see ``_ApplicationOnly``)."""


from BreastBiomechCommon import bindings  # noqa: E402
from BreastBiomechCommon.dependencies import (  # noqa: E402,F401  (re-exported for the modules)
    MissingDependencies,
    dependencies_ready,
    ensure_dependencies,
    skip_message,
    unmet_requirements,
)

# The Slicer modules the BreastBiomech modules use (``parent.dependencies``)
SLICER_MODULES = ["Volumes", "Segmentations", "Markups", "Models", "Tables", "Plots"]
CATEGORY = "Breast Biomechanics"  # the modules' category in Slicer's module list


class ModuleBase(ScriptedLoadableModule):
    """Base of the module classes: the extension's category, the Slicer modules every module
    uses (:data:`SLICER_MODULES`, plus ``more_dependencies``) and its contributors. A module sets
    its own ``parent.title``, ``helpText`` and ``acknowledgementText`` (each ``_(...)``, so that
    Slicer's translation tools find them)."""

    def __init__(self, parent, more_dependencies: tuple = ()):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.categories = [translate("qSlicerAbstractCoreModule", CATEGORY)]
        self.parent.dependencies = SLICER_MODULES + list(more_dependencies)
        self.parent.contributors = ["BreastBiomech contributors"]


class ModuleWidgetBase(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """Base of the module Widgets (Slicer's scripted-module template): :meth:`setup` loads the
    panel ``Resources/UI/<Module>.ui``, makes the Logic ``<Module>Logic`` of the module's file (the
    names Slicer itself finds ``<Module>Widget`` by) and observes the scene's close events. It
    connects the panel's bound widgets (those the file gives a parameter name:
    :mod:`BreastBiomechCommon.bindings`) and each push button ``<name>`` to the Widget's
    ``on<Name>`` where it has one, then calls :meth:`connectGUI` for the module's other signals
    (:meth:`connectLogic` for those that act on the scene). While the module is shown it observes
    the Logic's parameter node, dropping it on scene close: the node is shown on the panel through
    the bindings after :meth:`showParameters` (what they do not cover: enabled states, tables,
    labels, lists a bound combo box chooses from), and the panel stored in it through the bindings,
    then :meth:`storeParameters`. Testing/modules/test_ui_bindings.py checks the bindings against
    the Logic's parameters and the buttons against their handlers."""

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._updatingGUI = False
        self._bound = []  # (widget, kind, binding) of each bound widget of the panel, once set up
        self._worker = None  # the long step's process while it runs (startWorker)
        self._workerTimer = None

    def setup(self):
        import slicer

        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(resource_path(self.uiFile()))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = self.createLogic()
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        declared = bindings.read_bindings(resource_path(self.uiFile()))
        self._bound = [(getattr(self.ui, binding.widget), kind, binding) for binding, kind in declared]
        for widget, kind, _binding in self._bound:
            getattr(widget, bindings.SIGNAL_OF_KIND[kind]).connect(self.updateParameterNodeFromGUI)
        for button in bindings.button_names(resource_path(self.uiFile())):
            handler = getattr(self, bindings.handler_name(button), None)
            if handler is not None:
                getattr(self.ui, button).clicked.connect(handler)
        self.connectGUI()
        self.initializeParameterNode()

    @classmethod
    def moduleName(cls) -> str:
        return cls.__name__.removesuffix("Widget")

    @classmethod
    def uiFile(cls) -> str:
        """The panel's Qt Designer file, relative to ``Resources/``."""
        return f"UI/{cls.moduleName()}.ui"

    def createLogic(self):
        """The module's Logic: the class ``<Module>Logic`` of the module's file."""
        return getattr(sys.modules[type(self).__module__], self.moduleName() + "Logic")()

    def runAction(self, packages, failure: str, step):
        """A button's action: the Python ``packages`` it needs checked (offered for install; None
        when one is missing), then ``step(parameterNode)`` with any error shown in a dialog titled
        ``failure``; returns the step's result."""
        import slicer

        if not dependencies_ready(packages, slicer.util.getModule(self.moduleName()).title):
            return None
        with slicer.util.tryWithErrorDisplay(failure, waitCursor=True):
            return step(self._parameterNode)

    def connectLogic(self, signal, act) -> None:
        """A widget's ``signal`` calls ``act(parameterNode, *the signal's arguments)`` (a Logic step
        on the scene), neither while the panel is being updated from the parameter node nor
        without one."""
        def acted(*args):
            if self._parameterNode is not None and not self._updatingGUI:
                act(self._parameterNode, *args)

        signal.connect(acted)

    def updateGUIFromParameterNode(self, caller=None, event=None):
        """The parameter node shown on the panel (:meth:`showParameters`, then the bindings); the
        panel's own signals are not stored back meanwhile."""
        if self._parameterNode is None or self._updatingGUI:
            return
        self._updatingGUI = True
        try:
            self.showParameters(self._parameterNode)
            for widget, kind, binding in self._bound:
                bindings.show(widget, kind, binding, self._parameterNode)
        finally:
            self._updatingGUI = False

    def updateParameterNodeFromGUI(self, *args):
        """The panel stored in the parameter node (the bindings, then :meth:`storeParameters`) as
        one modification."""
        if self._parameterNode is None or self._updatingGUI:
            return
        wasModifying = self._parameterNode.node.StartModify()
        try:
            for widget, kind, binding in self._bound:
                bindings.store(widget, kind, binding, self._parameterNode)
            self.storeParameters(self._parameterNode)
        finally:
            self._parameterNode.node.EndModify(wasModifying)

    def connectGUI(self):
        """The module's signals beyond the bindings and the buttons' ``on<Name>`` (none here)."""

    def showParameters(self, parameterNode):
        """What the bindings do not show (enabled states, tables, labels); called before them."""

    def storeParameters(self, parameterNode):
        """What the bindings do not store; called after them."""

    def cleanup(self):
        """Leaving for good (module closed, application quit): a running step's process is stopped
        (what it finished is kept in its output folder)."""
        self.cancelWorker()
        self.removeObservers()

    # -- long steps out of Slicer's process (BreastBiomechCommon.worker) ---------------------------

    def startWorker(self, worker, ended, progressBar=None, statusLabel=None) -> None:
        """Follow the started ``worker`` from a timer (every ``POLL_INTERVAL_MS``) while Slicer
        stays live: its latest progress into ``progressBar`` (value and text) and
        ``statusLabel``; once it has ended (finished, failed or cancelled) the timer stops and
        ``ended(worker)`` runs (the Logic's finishing step, in an error display)."""
        import qt
        from BreastBiomechCommon.worker import POLL_INTERVAL_MS

        if self._workerTimer is None:
            self._workerTimer = qt.QTimer()
            self._workerTimer.setInterval(POLL_INTERVAL_MS)
            self._workerTimer.timeout.connect(self._pollWorker)
        self._worker, self._workerEnded, self._workerViews = worker, ended, (progressBar, statusLabel)
        self._workerTimer.start()

    def _pollWorker(self):
        worker = self._worker
        if worker is None:
            self._workerTimer.stop()
            return
        worker.poll()
        progressBar, statusLabel = self._workerViews
        if worker.last is not None:
            fraction = worker.last.get("fraction")
            if progressBar is not None:
                if fraction is not None:
                    progressBar.value = int(100 * fraction)
                progressBar.setFormat(worker.last["message"])
            if statusLabel is not None:
                statusLabel.text = worker.last["message"]
        if worker.running:
            return
        self._workerTimer.stop()
        self._worker = None
        self._workerEnded(worker)

    def cancelWorker(self) -> float:
        """Stop the running step's process (its finishing step then reports the cancel); the
        seconds it took to stop (0: none was running)."""
        if self._worker is None or not self._worker.running:
            return 0.0
        return self._worker.cancel()

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


class ModuleTestMixin:
    """Base of the module self-tests (mix in before ``ScriptedLoadableModuleTest``): ``REQUIRES``
    names the packages (import names) the tests need; where one is missing or too old, the test
    is skipped with the reason and how to install it, not failed with an ImportError, and the skip
    is raised (``unittest.SkipTest``), so that it is not taken for a pass. ``runTest`` (what
    ``slicer.selfTests[module]()`` and Reload and Test call) runs every ``test_*`` method."""

    REQUIRES: tuple = ()

    def setUp(self):
        unmet = unmet_requirements(self.REQUIRES)
        if unmet:
            self.skipTest(skip_message(unmet))
        import slicer

        slicer.mrmlScene.Clear()

    def runTest(self):
        for name in sorted(n for n in dir(self) if n.startswith("test_")):
            try:
                self.setUp()
            except unittest.SkipTest as skipped:
                logging.warning("%s skipped: %s", type(self).__name__, skipped)
                self.delayDisplay(f"{type(self).__name__} skipped: {skipped}")
                raise  # a skip is reported as one (ctest: skipped; Reload and Test: the reason), never as a pass
            getattr(self, name)()


class ModuleLogicBase:
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


def chosen_folder(path: str, what: str) -> str:
    """``path`` as chosen in a folder field: refused when nothing was chosen ("" or ".", what an
    empty folder widget reports) or when relative (it would resolve against Slicer's working
    folder, which the user never chose). ``what`` names the folder in the message."""
    if not path or path.strip() in (".", "./"):
        raise ValueError(f"choose {what}")
    if not os.path.isabs(path):
        raise ValueError(f"{what.split(' (')[0]} must be an absolute path, not {path!r} (a relative path would "
                         "point into Slicer's working folder)")
    return path


def ensure_library_importable() -> None:
    """Make ``import BreastBiomechLib`` work when the modules run from a source checkout (the
    checkout's root is appended to ``sys.path``, so it never shadows an installed package)."""
    if importlib.util.find_spec("BreastBiomechLib") is None and os.path.isdir(
            os.path.join(_SOURCE_ROOT, "BreastBiomechLib")):
        sys.path.append(_SOURCE_ROOT)


def resource_path(relative: str) -> str:
    """Absolute path of a module resource, e.g. ``resource_path("UI/BreastBiomech.ui")``: the
    ``Resources/`` folder beside the module scripts, where Slicer also looks for the icons and
    the developer section's "Edit UI" for the panels, in a source checkout and a built extension."""
    candidate = os.path.join(_HERE, "Resources", relative)
    if not os.path.exists(candidate):
        raise FileNotFoundError(f"BreastBiomech resource {relative!r} not found in {os.path.join(_HERE, 'Resources')}")
    return candidate
