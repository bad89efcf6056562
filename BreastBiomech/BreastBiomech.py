"""BreastBiomech: the extension's home module.

Generates a synthetic breast MR case (the built-in phantom) straight into the scene: the MR
volume, the ground-truth tissue segmentation, the per-tissue fraction volumes and the 17
landmarks. Also registers the "Breast phantom" sample data entry.

Module, Widget, Logic and Test classes follow Slicer's scripted-module template. The Logic holds
no Qt and runs headless on the ``slicer-core`` wheel (see docs/developing.md).
"""

from __future__ import annotations

import logging
import os

import slicer
from BreastBiomechCommon import (
    IN_SLICER_APPLICATION,
    ParameterNodeLogic,
    ParameterNodeWidgetMixin,
    ScriptedLoadableModule,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
    ensure_dependencies,
    ensure_library_importable,
    resource_path,
)
from slicer.util import VTKObservationMixin

ensure_library_importable()

CATEGORY = "Breast Biomechanics"
SAMPLE_NAME = "Breast phantom"


#
# Module
#


class BreastBiomech(ScriptedLoadableModule):
    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "BreastBiomech"
        self.parent.categories = [CATEGORY]
        self.parent.dependencies = []
        self.parent.contributors = ["BreastBiomech contributors"]
        self.parent.helpText = (
            "Patient-specific biomechanical breast models from MR. This home module generates the "
            "built-in breast phantom (MR, tissue labels, partial-volume fractions, 17 landmarks) "
            "and is the starting point of the pipeline. See the "
            "<a href='https://github.com/BreastBiomech/BreastBiomech'>project page</a>."
        )
        self.parent.acknowledgementText = (
            "Method after Han et al. 2012, Phys. Med. Biol. 57:455 (patient-specific breast "
            "biomechanics with a GPU TLED solver and image-based material optimisation)."
        )
        slicer.app.connect("startupCompleted()", registerSampleData)


def registerSampleData():
    """Add "Breast phantom" to the Sample Data module: generated, not downloaded."""
    import SampleData

    SampleData.SampleDataLogic.registerCustomSampleDataSource(
        category=CATEGORY,
        sampleName=SAMPLE_NAME,
        uris=[],
        fileNames=[],
        nodeNames=[],
        loadFileType=[],
        thumbnailFileName=resource_path("Icons/BreastPhantom.png"),
        customDownloader=_loadSamplePhantom,
    )


def _loadSamplePhantom(source=None):
    if not ensure_dependencies(["scipy", "SimpleITK", "matplotlib"]):
        return []
    from BreastBiomechLib.phantom import table1_case

    logic = BreastBiomechLogic()
    with slicer.util.tryWithErrorDisplay("Failed to generate the breast phantom.", waitCursor=True):
        nodes = logic.loadPhantom(table1_case(2))
        logic.showPhantom(nodes)
        return [nodes["volume"]]
    return []


#
# Widget
#


class BreastBiomechWidget(ParameterNodeWidgetMixin, ScriptedLoadableModuleWidget, VTKObservationMixin):
    """Thin GUI: reads and writes the parameter node, calls the Logic, shows the result."""

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._updatingGUI = False

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(resource_path("UI/BreastBiomech.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = BreastBiomechLogic()

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)

        self.ui.caseComboBox.currentIndexChanged.connect(self.onCaseChanged)
        for spinBox in (self.ui.seedSpinBox,):
            spinBox.valueChanged.connect(self.updateParameterNodeFromGUI)
        for slider in self._sliders():
            slider.valueChanged.connect(self.updateParameterNodeFromGUI)
        self.ui.skinSeparateCheckBox.toggled.connect(self.updateParameterNodeFromGUI)
        self.ui.generateButton.clicked.connect(self.onGenerateButton)
        self.ui.loadFolderButton.clicked.connect(self.onLoadFolderButton)
        self.initializeParameterNode()

    def _sliders(self):
        return (self.ui.volumeSliderWidget, self.ui.densitySliderWidget, self.ui.tumourSliderWidget,
                self.ui.snrSliderWidget, self.ui.biasSliderWidget)

    def updateGUIFromParameterNode(self, caller=None, event=None):
        if self._parameterNode is None or self._updatingGUI:
            return
        self._updatingGUI = True
        try:
            p = self._parameterNode
            self.ui.caseComboBox.currentIndex = p["case"]
            self.ui.seedSpinBox.value = p["seed"]
            self.ui.volumeSliderWidget.value = p["volumeCm3"]
            self.ui.densitySliderWidget.value = p["density"] * 100.0
            self.ui.tumourSliderWidget.value = p["tumourMm"]
            self.ui.snrSliderWidget.value = p["snr"]
            self.ui.biasSliderWidget.value = p["bias"] * 100.0
            self.ui.skinSeparateCheckBox.checked = p["skinSeparate"]
            custom = p["case"] == 0
            for widget in (self.ui.seedSpinBox, *self._sliders()):
                widget.enabled = custom
        finally:
            self._updatingGUI = False

    def updateParameterNodeFromGUI(self, *args):
        if self._parameterNode is None or self._updatingGUI:
            return
        p = self._parameterNode
        wasModifying = p.node.StartModify()
        p["case"] = self.ui.caseComboBox.currentIndex
        p["seed"] = self.ui.seedSpinBox.value
        p["volumeCm3"] = self.ui.volumeSliderWidget.value
        p["density"] = self.ui.densitySliderWidget.value / 100.0
        p["tumourMm"] = self.ui.tumourSliderWidget.value
        p["snr"] = self.ui.snrSliderWidget.value
        p["bias"] = self.ui.biasSliderWidget.value / 100.0
        p["skinSeparate"] = self.ui.skinSeparateCheckBox.checked
        p.node.EndModify(wasModifying)

    def onCaseChanged(self, index):
        if self._parameterNode is None or self._updatingGUI:
            return
        self.logic.applyCasePreset(self._parameterNode, index)

    def onGenerateButton(self):
        if not ensure_dependencies(["scipy", "SimpleITK", "matplotlib"]):
            return
        with slicer.util.tryWithErrorDisplay("Failed to generate the breast phantom.", waitCursor=True):
            params = self.logic.phantomParameters(self._parameterNode)
            progress = slicer.util.createProgressDialog(labelText="Generating the breast phantom...", maximum=100)
            try:
                def report(fraction, message):
                    progress.labelText = message
                    progress.value = int(100 * fraction)
                    slicer.app.processEvents()

                nodes = self.logic.loadPhantom(params, progress=report)
            finally:
                progress.close()
            self.logic.showPhantom(nodes)
            self.ui.summaryLabel.text = self.logic.summaryText(nodes["summary"])

    def onLoadFolderButton(self):
        folder = self.ui.caseFolderPathLineEdit.currentPath
        with slicer.util.tryWithErrorDisplay("Failed to load the phantom case folder.", waitCursor=True):
            nodes = self.logic.loadPhantomFolder(folder)
            self.logic.showPhantom(nodes)
            self.ui.summaryLabel.text = self.logic.summaryText(nodes["summary"])


#
# Logic
#


class BreastBiomechLogic(ParameterNodeLogic):
    """Phantom cases into MRML nodes. No Qt: runs in Slicer and headless (slicer-core wheel).

    ``scene`` defaults to ``slicer.mrmlScene`` inside the application."""

    MODULE_NAME = "BreastBiomech"
    DEFAULTS = {"case": 0, "seed": 1, "volumeCm3": 800.0, "density": 0.25, "tumourMm": 0.0,
                "snr": 30.0, "bias": 0.2, "skinSeparate": False}
    ROLES = ("mrVolume", "segmentation", "landmarks")

    def applyCasePreset(self, parameterNode, case: int) -> None:
        """Set ``case`` (0 = custom, 1-5 = the seed's Table 1) and copy that preset's values."""
        from BreastBiomechLib.phantom import table1_case

        wasModifying = parameterNode.node.StartModify()
        parameterNode["case"] = case
        if case:
            preset = table1_case(case)
            parameterNode["seed"] = preset.seed
            parameterNode["volumeCm3"] = preset.volume_cm3
            parameterNode["density"] = preset.density
            parameterNode["tumourMm"] = preset.tumour_diameter_mm
            parameterNode["snr"] = preset.snr
            parameterNode["bias"] = preset.bias_strength
        parameterNode.node.EndModify(wasModifying)

    def phantomParameters(self, parameterNode):
        """PhantomParameters from the parameter node (a Table 1 preset, or the custom values)."""
        from BreastBiomechLib.phantom import PhantomParameters, table1_case

        p = parameterNode
        base = table1_case(p["case"]) if p["case"] else PhantomParameters()
        values = base.to_dict()
        values.update(seed=p["seed"], volume_cm3=p["volumeCm3"], density=p["density"],
                      tumour_diameter_mm=p["tumourMm"], snr=p["snr"], bias_strength=p["bias"],
                      skin_separate=p["skinSeparate"])
        return PhantomParameters.from_dict(values)

    def loadPhantom(self, params, progress=None, name: str = "BreastPhantom") -> dict:
        """Generate a phantom case and put it into the scene; returns its nodes and summary."""
        from BreastBiomechLib.phantom import generate_phantom

        case = generate_phantom(params, progress=progress)
        return self.addCaseToScene(case, name)

    def loadPhantomFolder(self, folder: str, name: str | None = None) -> dict:
        """Load a case folder written by ``breastbiomech phantom --out DIR``."""
        from BreastBiomechLib.phantom import read_phantom

        if not folder:
            raise ValueError("choose a phantom case folder (made with `breastbiomech phantom --out DIR`)")
        case = read_phantom(folder)
        return self.addCaseToScene(case, name or os.path.basename(os.path.normpath(folder)))

    def addCaseToScene(self, case, name: str) -> dict:
        """MR volume, tissue segmentation, fraction volumes, landmarks and seed point lists (for
        the Breast Segmentation module: on the muscle and, if any, in the tumour) of ``case`` as
        nodes."""
        from BreastBiomechLib import mrml
        from BreastBiomechLib.phantom.files import SEED_COUNTS
        from BreastBiomechLib.phantom.seeds import seed_points

        volume = mrml.image_to_volume_node(case.image, self.scene, f"{name}_MR")
        segmentation = mrml.labels_to_segmentation_node(case.labels, self.scene, f"{name}_Tissues")
        segmentation.SetReferenceImageGeometryParameterFromVolumeNode(volume)
        fractions = {tissue: mrml.image_to_volume_node(image, self.scene, f"{name}_fraction_{tissue}")
                     for tissue, image in case.fractions.items()}
        landmarks = mrml.landmarks_to_markups_node(case.landmarks, self.scene, f"{name}_Landmarks")
        seeds = {tissue: mrml.landmarks_to_markups_node(seed_points(case.labels, tissue, count), self.scene,
                                                        f"{name}_Seeds_{tissue}", locked=False)
                 for tissue, count in SEED_COUNTS.items() if case.summary["tissue_volumes_cm3"].get(tissue, 0.0) > 0}
        parameterNode = self.getParameterNode()
        parameterNode.set_reference("mrVolume", volume)
        parameterNode.set_reference("segmentation", segmentation)
        parameterNode.set_reference("landmarks", landmarks)
        logging.info("BreastBiomech: %s", self.summaryText(case.summary))
        return {"volume": volume, "segmentation": segmentation, "fractions": fractions,
                "landmarks": landmarks, "seeds": seeds, "summary": case.summary}

    def showPhantom(self, nodes: dict) -> None:
        """Show the MR in the slice views with the segmentation outlined (application only)."""
        if not IN_SLICER_APPLICATION:
            return
        slicer.util.setSliceViewerLayers(background=nodes["volume"], fit=True)
        display = nodes["segmentation"].GetDisplayNode()
        if display is not None:
            display.SetAllSegmentsVisibility2DFill(False)
        nodes["segmentation"].CreateClosedSurfaceRepresentation()
        nipple = nodes["landmarks"].GetControlPointIndexByLabel("nipple")
        if nipple >= 0:
            slicer.modules.markups.logic().JumpSlicesToNthPointInMarkup(nodes["landmarks"].GetID(), nipple, True)

    @staticmethod
    def summaryText(summary: dict) -> str:
        volumes = ", ".join(f"{k} {v:.0f}" for k, v in summary["tissue_volumes_cm3"].items())
        return (f"breast {summary['breast_volume_cm3']:.0f} cm³, glandular density "
                f"{summary['glandular_density']:.0%}; tissue volumes (cm³): {volumes}")


#
# Test (runs inside Slicer: Reload and Test; the same checks run headless in Testing/)
#


class BreastBiomechTest(ScriptedLoadableModuleTest):
    def setUp(self):
        slicer.mrmlScene.Clear()

    def runTest(self):
        self.setUp()
        self.test_phantom_into_scene()

    def test_phantom_into_scene(self):
        from BreastBiomechLib.phantom import PhantomParameters

        self.delayDisplay("Generating a small breast phantom")
        logic = BreastBiomechLogic()
        nodes = logic.loadPhantom(PhantomParameters(seed=2, volume_cm3=450.0, spacing_mm=(2.0, 2.0, 3.0)))
        self.assertEqual(nodes["landmarks"].GetNumberOfControlPoints(), 17)
        segmentation = nodes["segmentation"].GetSegmentation()
        self.assertIsNotNone(segmentation.GetSegment("glandular"))
        self.assertAlmostEqual(nodes["summary"]["breast_volume_cm3"], 450.0, delta=15.0)
        logic.showPhantom(nodes)
        self.delayDisplay("Test passed")
