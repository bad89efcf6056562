"""BreastBiomech: the extension's home module.

Generates a synthetic breast MR case (the built-in phantom) straight into the scene: the MR
volume, the ground-truth tissue segmentation, the per-tissue fraction volumes and the 17
landmarks. Also registers the "Breast phantom" sample data entry: a phantom shipped in
``Resources/SampleData`` (MR, tissue segmentation, landmarks), loaded by Slicer's own readers,
so ``SampleData.downloadSample("Breast phantom")`` works from a script as the button does.

Module, Widget, Logic and Test classes follow Slicer's scripted-module template. The Logic holds
no Qt and runs headless on the ``slicer-core`` wheel (see docs/developing.md).
"""

from __future__ import annotations

import logging
import os
import pathlib

import slicer
from BreastBiomechCommon import (CATEGORY, IN_SLICER_APPLICATION, ModuleBase, ModuleLogicBase, ModuleTestMixin,
                                 ModuleWidgetBase, ScriptedLoadableModuleTest, _, dependencies_ready,
                                 ensure_library_importable, resource_path)

ensure_library_importable()

DEPENDENCIES = ["numpy", "scipy", "SimpleITK", "matplotlib"]  # generating a phantom
SAMPLE_NAME = "Breast phantom"
# The shipped sample: Table 1 case 2 of the seed at 2 x 2 x 3 mm voxels (made by
# BreastBiomechLogic.writeSampleData; the test in Testing/modules/test_module_breastbiomech.py regenerates it)
SAMPLE_CASE = 2
SAMPLE_SPACING_MM = (2.0, 2.0, 3.0)
SAMPLE_MR_SCALE = 1000.0  # the MR is stored as uint16: the phantom's signal x 1000
SAMPLE_FILES = (  # file name, node name, Slicer file type
    ("BreastPhantom_MR.nrrd", "BreastPhantom_MR", "VolumeFile"),
    ("BreastPhantom_Tissues.seg.nrrd", "BreastPhantom_Tissues", "SegmentationFile"),
    ("BreastPhantom_Landmarks.mrk.json", "BreastPhantom_Landmarks", "MarkupsFile"),
)


class BreastBiomech(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent, ("SampleData",))
        self.parent.title = _("BreastBiomech")
        self.parent.helpText = _("""
Patient-specific biomechanical breast models from MR. This home module generates the built-in breast
phantom (MR, tissue labels, partial-volume fractions, 17 landmarks) and is the starting point of the
pipeline. See the <a href='https://github.com/BreastBiomech/BreastBiomech'>project page</a>.
""")
        self.parent.acknowledgementText = _("""
Method after Han et al. 2012, Phys. Med. Biol. 57:455 (patient-specific breast biomechanics with a GPU
TLED solver and image-based material optimisation).
""")
        slicer.app.connect("startupCompleted()", registerSampleData)


def sampleDataArguments() -> dict:
    """The "Breast phantom" entry for ``SampleData.SampleDataLogic.registerCustomSampleDataSource``:
    the shipped files as ``file://`` URIs with their SHA-256 checksums, loaded by Slicer's readers
    (MR volume, tissue segmentation, landmarks; the MR node is the first)."""
    import hashlib

    paths = [pathlib.Path(resource_path(f"SampleData/{name}")) for name, _node, _type in SAMPLE_FILES]
    return {
        "category": CATEGORY,
        "sampleName": SAMPLE_NAME,
        "uris": [path.resolve().as_uri() for path in paths],
        "fileNames": [name for name, _node, _type in SAMPLE_FILES],
        "nodeNames": [node for _name, node, _type in SAMPLE_FILES],
        "loadFileType": [kind for _name, _node, kind in SAMPLE_FILES],
        "checksums": [f"SHA256:{hashlib.sha256(path.read_bytes()).hexdigest()}" for path in paths],
        "thumbnailFileName": resource_path("Icons/BreastPhantom.png"),
    }


def registerSampleData():
    """Add "Breast phantom" to the Sample Data module (its button and ``downloadSample``)."""
    import SampleData

    SampleData.SampleDataLogic.registerCustomSampleDataSource(**sampleDataArguments())


class BreastBiomechWidget(ModuleWidgetBase):
    def connectGUI(self):
        self.connectLogic(self.ui.caseComboBox.currentIndexChanged, self.logic.applyCasePreset)

    def showParameters(self, p):
        # the case is an index (choosing one applies its preset: connectGUI), stored below
        self.ui.caseComboBox.currentIndex = p["case"]
        custom = p["case"] == 0
        for widget in (self.ui.seedSpinBox, self.ui.volumeSliderWidget, self.ui.densitySliderWidget,
                       self.ui.tumourSliderWidget, self.ui.snrSliderWidget, self.ui.biasSliderWidget):
            widget.enabled = custom

    def storeParameters(self, p):
        p["case"] = self.ui.caseComboBox.currentIndex

    def onGenerateButton(self):
        if not dependencies_ready(DEPENDENCIES, _("BreastBiomech")):
            return
        with slicer.util.tryWithErrorDisplay(_("Failed to generate the breast phantom."), waitCursor=True):
            params = self.logic.phantomParameters(self._parameterNode)
            progress = slicer.util.createProgressDialog(labelText=_("Generating the breast phantom..."), maximum=100)
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
        if not dependencies_ready(DEPENDENCIES, _("BreastBiomech")):
            return
        folder = self.ui.caseFolderPathLineEdit.currentPath
        with slicer.util.tryWithErrorDisplay(_("Failed to load the phantom case folder."), waitCursor=True):
            nodes = self.logic.loadPhantomFolder(folder)
            self.logic.showPhantom(nodes)
            self.ui.summaryLabel.text = self.logic.summaryText(nodes["summary"])


class BreastBiomechLogic(ModuleLogicBase):
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

        if not folder or os.path.normpath(folder) == ".":  # an empty path field reads "" or "."
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

    def writeSampleData(self, folder: str) -> list[str]:
        """Write the shipped "Breast phantom" sample (``SAMPLE_FILES``) into ``folder``: Table 1
        case ``SAMPLE_CASE`` at ``SAMPLE_SPACING_MM``, the MR as uint16 (signal x
        ``SAMPLE_MR_SCALE``), the true tissues as a Slicer segmentation, the 17 landmarks. Returns
        the paths. Maintainers run it after changing the phantom generator (docs/developing.md)."""
        import dataclasses

        import SimpleITK as sitk

        from BreastBiomechLib import mrml
        from BreastBiomechLib.io.markups import write_markups
        from BreastBiomechLib.phantom import generate_phantom, table1_case

        out = pathlib.Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        case = generate_phantom(dataclasses.replace(table1_case(SAMPLE_CASE), spacing_mm=SAMPLE_SPACING_MM))
        paths = [out / name for name, _node, _type in SAMPLE_FILES]
        mr = sitk.Cast(sitk.Clamp(sitk.Round(case.image * SAMPLE_MR_SCALE), lowerBound=0, upperBound=65535),
                       sitk.sitkUInt16)
        sitk.WriteImage(mr, str(paths[0]), True)
        segmentation = mrml.labels_to_segmentation_node(case.labels, self.scene, SAMPLE_FILES[1][1])
        storage = self.scene.AddNewNodeByClass("vtkMRMLSegmentationStorageNode")
        storage.SetFileName(str(paths[1]))
        storage.SetUseCompression(True)
        if not storage.WriteData(segmentation):
            raise OSError(f"could not write {paths[1]}")
        self.scene.RemoveNode(storage)
        self.scene.RemoveNode(segmentation)
        write_markups(paths[2], case.landmarks, name=SAMPLE_FILES[2][1])
        return [str(path) for path in paths]

    @staticmethod
    def summaryText(summary: dict) -> str:
        volumes = ", ".join(f"{k} {v:.0f}" for k, v in summary["tissue_volumes_cm3"].items())
        return (f"breast {summary['breast_volume_cm3']:.0f} cm³, glandular density "
                f"{summary['glandular_density']:.0%}; tissue volumes (cm³): {volumes}")


#
# Test (runs inside Slicer: Reload and Test; the same checks run headless in Testing/)
#


class BreastBiomechTest(ModuleTestMixin, ScriptedLoadableModuleTest):
    REQUIRES = tuple(DEPENDENCIES)

    def test_sample_data_from_a_script(self):
        import SampleData

        registerSampleData()
        nodes = SampleData.SampleDataLogic().downloadSamples(SAMPLE_NAME)
        self.assertEqual([node.GetName() for node in nodes], [node for _name, node, _type in SAMPLE_FILES])
        self.assertEqual(nodes[2].GetNumberOfControlPoints(), 17)
        self.assertIsNotNone(nodes[1].GetSegmentation().GetSegment("glandular"))

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
