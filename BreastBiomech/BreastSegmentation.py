"""BreastSegmentation: tissue classification of a breast MR volume (seed section 2.2.1).

Choose the MR volume and seed points (markups) on the pectoral muscle and, if there is one, in the
tumour; then, one step at a time or all at once: grow the muscle, grow the tumour, classify the
breast in front of the muscle into fat and glandular tissue (EM with a Markov-random-field prior
and bias-field correction). Results go into a segmentation node with the label table's segment
names and colours, editable in the Segment Editor between steps (each step reads the segments as
they are), plus probability volumes per tissue, the estimated bias field and a volumes table.

Module, Widget, Logic and Test classes follow Slicer's scripted-module template. The Logic holds
no Qt and runs headless on the ``slicer-core`` wheel (see docs/developing.md).
"""

from __future__ import annotations

import logging

import numpy as np
import slicer
from BreastBiomechCommon import (IN_SLICER_APPLICATION, ModuleBase, ModuleLogicBase, ModuleTestMixin,
                                 ModuleWidgetBase, ScriptedLoadableModuleTest, _, dependencies_ready,
                                 ensure_library_importable)

ensure_library_importable()

DEPENDENCIES = ["numpy", "scipy", "SimpleITK"]


class StepCancelled(Exception):
    """The user stopped a segmentation step; the scene is as it was before the step."""


class BreastSegmentation(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent)
        self.parent.title = _("Breast Segmentation")
        self.parent.helpText = _("""
Tissue classification of a breast MR volume: pectoral muscle and tumour grown from seed points, fat and
fibroglandular tissue by expectation-maximisation with a Markov-random-field prior, bias-field
correction and a partial-volume class; probabilities per tissue. Edit the segments in the Segment Editor
between steps. See docs/segmentation.md of the
<a href='https://github.com/BreastBiomech/BreastBiomech'>project</a>.
""")
        self.parent.acknowledgementText = _("""
Method after Han et al. 2012, Phys. Med. Biol. 57:455, whose fat/glandular step used NiftySeg's EM
(Cardoso et al. 2011); partial-volume and bias models after Van Leemput et al. 1999 and 2003.
""")


class BreastSegmentationWidget(ModuleWidgetBase):
    def __init__(self, parent=None):
        ModuleWidgetBase.__init__(self, parent)
        self._running = False
        self._cancelRequested = False

    def connectGUI(self):
        self.ui.muscleButton.clicked.connect(lambda: self.onStep(self.logic.segmentMuscle, "Muscle segmentation failed."))
        self.ui.tumourButton.clicked.connect(lambda: self.onStep(self.logic.segmentTumour, "Tumour segmentation failed."))
        self.ui.tissuesButton.clicked.connect(lambda: self.onStep(self.logic.classifyTissues, "Classification failed."))
        self.ui.allButton.clicked.connect(lambda: self.onStep(self.logic.runAll, "Segmentation failed."))

    def showParameters(self, p):
        self.ui.volumesTableView.setMRMLTableNode(p.reference("volumesTable"))
        # a step runs alone: while one runs (it processes events) the others wait, Cancel stops it
        ready = p.reference("inputVolume") is not None and not self._running
        haveMuscleSeeds = p.reference("muscleSeeds") is not None
        self.ui.muscleButton.enabled = ready and haveMuscleSeeds
        self.ui.tumourButton.enabled = ready and p.reference("tumourSeeds") is not None
        self.ui.tissuesButton.enabled = ready and p.reference("outputSegmentation") is not None
        self.ui.allButton.enabled = ready and haveMuscleSeeds
        self.ui.cancelButton.enabled = self._running

    def onCancelButton(self):
        self._cancelRequested = True

    def _setRunning(self, running):
        self._running = running
        self.updateGUIFromParameterNode()

    def onStep(self, step, errorMessage):
        if self._running or not dependencies_ready(DEPENDENCIES, _("Breast Segmentation")):
            return
        self._cancelRequested = False
        self._setRunning(True)
        self.ui.progressBar.value = 0

        def report(fraction, message):
            self.ui.progressBar.value = int(100 * fraction)
            self.ui.progressBar.setFormat(f"{message} (%p%)")
            slicer.app.processEvents()
            return not self._cancelRequested

        try:
            with slicer.util.tryWithErrorDisplay(_(errorMessage), waitCursor=True):
                try:
                    self.ui.statusLabel.text = step(self._parameterNode, progress=report)
                except StepCancelled as cancelled:
                    self.ui.statusLabel.text = str(cancelled)
                    return
                self.logic.showResults(self._parameterNode)
        finally:
            self._setRunning(False)


class BreastSegmentationLogic(ModuleLogicBase):
    """MR volume node + seed point lists -> BreastBiomechLib.segmentation -> segmentation node
    (segments named and coloured by the label table), probability and bias-field volume nodes,
    and a volumes table. No Qt: runs in Slicer and headless (slicer-core wheel).

    Each step returns a one-paragraph summary for the panel. ``progress(fraction, message)``
    answering False stops a step (:class:`StepCancelled`) before it writes anything. Seeds are read in world coordinates
    (RAS, parent transforms applied) and handed to the library in LPS. ``scene`` defaults to
    ``slicer.mrmlScene``."""

    MODULE_NAME = "BreastSegmentation"
    DEFAULTS = {"mrfStrength": 0.4, "biasOrder": 3, "maxIterations": 40, "partialVolume": True,
                "fractionSmoothing": 0.2, "skinMm": 3.0, "keepSkin": False, "tissueOnFascia": True}
    ROLES = ("inputVolume", "muscleSeeds", "tumourSeeds", "outputSegmentation", "biasField", "volumesTable",
             "probabilityFat", "probabilityGlandular", "probabilityMuscle", "probabilityTumour", "probabilitySkin")

    # -- inputs ----------------------------------------------------------------------------------

    def settings(self, parameterNode):
        """The library SegmentationSettings of the current choices."""
        from BreastBiomechLib.segmentation import EMSettings, FasciaSettings, SegmentationSettings

        p = parameterNode
        return SegmentationSettings(
            em=EMSettings(mrf_strength=p["mrfStrength"], bias_order=int(p["biasOrder"]),
                          max_iterations=int(p["maxIterations"]), partial_volume=p["partialVolume"],
                          fraction_smoothing=p["fractionSmoothing"]),
            skin_mm=p["skinMm"], keep_skin=p["keepSkin"],
            fascia=FasciaSettings() if p["tissueOnFascia"] else None)

    def inputImage(self, parameterNode):
        """The MR volume as a SimpleITK image (LPS)."""
        from BreastBiomechLib.mrml import image_from_volume_node

        node = parameterNode.reference("inputVolume")
        if node is None:
            raise ValueError("choose the MR volume to segment")
        return image_from_volume_node(node)

    @staticmethod
    def seedPositions(parameterNode, role: str, required: bool):
        """The defined points of the seed list ``role`` (LPS mm); None when no list is chosen and
        the seeds are optional."""
        from BreastBiomechLib.mrml import landmarks_from_markups_node

        what = {"muscleSeeds": "pectoral muscle", "tumourSeeds": "tumour"}[role]
        node = parameterNode.reference(role)
        if node is None:
            if required:
                raise ValueError(f"choose a point list with seeds on the {what} (3-5 points spread over it)")
            return None
        positions = landmarks_from_markups_node(node).positions
        if len(positions) == 0:
            raise ValueError(f"the point list {node.GetName()!r} has no placed points; click seeds on the {what}")
        return positions

    def segmentationNode(self, parameterNode):
        """The output segmentation node, made (named after the volume, geometry from it) if none."""
        p = parameterNode
        node = p.reference("outputSegmentation")
        if node is None:
            volume = p.reference("inputVolume")
            base = volume.GetName() if volume is not None else "Breast"
            node = self.scene.AddNewNodeByClass("vtkMRMLSegmentationNode", self.scene.GenerateUniqueName(f"{base}_tissues"))
            node.CreateDefaultDisplayNodes()
            if volume is not None:
                node.SetReferenceImageGeometryParameterFromVolumeNode(volume)
            p.set_reference("outputSegmentation", node)
        return node

    def segmentMask(self, parameterNode, tissue: str, image):
        """The segment named ``tissue`` of the output segmentation as a mask on the volume's grid,
        or None when there is no such segment (or it is empty)."""
        from BreastBiomechLib.mrml import mask_from_segment

        node = parameterNode.reference("outputSegmentation")
        if node is None:
            return None
        import SimpleITK as sitk

        mask = mask_from_segment(node, tissue, self.scene, image)
        if mask is None or not np.any(sitk.GetArrayViewFromImage(mask)):
            return None
        return mask

    # -- steps -----------------------------------------------------------------------------------

    @staticmethod
    def _reporter(progress, step: str):
        """The progress callback handed to the library: passes ``progress`` on, and raises
        :class:`StepCancelled` where it answers False (the library calls it between stages, before
        the Logic writes anything to the scene)."""
        def report(fraction, message):
            if progress is not None and progress(fraction, message) is False:
                raise StepCancelled(f"{step} cancelled at {100 * fraction:.0f} % ({message}); the segmentation "
                                    "is as it was before the step")
        return report

    def segmentMuscle(self, parameterNode, progress=None) -> str:
        """Step 1: grow the pectoral muscle from its seeds into the ``muscle`` segment (replaced;
        other segments kept) and its probability volume."""
        from BreastBiomechLib.segmentation import segment_muscle

        report = self._reporter(progress, "Pectoral muscle segmentation")
        p = parameterNode
        image = self.inputImage(p)
        seeds = self.seedPositions(p, "muscleSeeds", required=True)
        report(0.0, "pectoral muscle from seeds")
        muscle = segment_muscle(image, seeds, self.settings(p))
        report(0.9, "writing the muscle segment")
        self._writeStructure(p, "muscle", muscle)
        return f"Pectoral muscle: {self._volume_cm3(muscle.mask):.0f} cm³ from {len(seeds)} seeds. " \
               "Check it (and edit it in the Segment Editor) before the next steps: it delimits the breast."

    def segmentTumour(self, parameterNode, progress=None) -> str:
        """Step 2: grow the tumour from its seeds inside the breast that the (possibly edited)
        ``muscle`` segment delimits; into the ``tumour`` segment and its probability volume."""
        from BreastBiomechLib.segmentation import segment_tumour

        report = self._reporter(progress, "Tumour segmentation")
        p = parameterNode
        image = self.inputImage(p)
        seeds = self.seedPositions(p, "tumourSeeds", required=True)
        muscle = self._requireMuscle(p, image)
        report(0.0, "tumour from seeds")
        tumour = segment_tumour(image, muscle, seeds, self.settings(p))
        report(0.9, "writing the tumour segment")
        self._writeStructure(p, "tumour", tumour)
        volume = self._volume_cm3(tumour.mask)
        diameter = (6 * volume * 1000 / np.pi) ** (1 / 3)
        return f"Tumour: {volume:.2f} cm³ (equivalent diameter {diameter:.1f} mm) from {len(seeds)} seeds."

    def classifyTissues(self, parameterNode, progress=None) -> str:
        """Step 3: fat / glandular classification of the breast in front of the ``muscle``
        segment (the ``tumour`` segment, if any, kept out), all segments rewritten from the
        merged label map (muscle and tumour exactly as they were), plus probabilities, bias field
        and volumes table."""
        from BreastBiomechLib.segmentation import classify_tissues

        p = parameterNode
        image = self.inputImage(p)
        muscle = self._requireMuscle(p, image)
        tumour = self.segmentMask(p, "tumour", image)
        result = classify_tissues(image, muscle, tumour, self.settings(p),
                                  progress=self._reporter(progress, "Fat / glandular classification"))
        self.writeResults(p, result)
        return self.summaryText(result)

    def runAll(self, parameterNode, progress=None) -> str:
        """All steps from the seeds in one go (the library's segment_tissues); replaces the
        output segmentation's segments."""
        from BreastBiomechLib.segmentation import segment_tissues

        p = parameterNode
        image = self.inputImage(p)
        muscle = self.seedPositions(p, "muscleSeeds", required=True)
        tumour = self.seedPositions(p, "tumourSeeds", required=False)
        result = segment_tissues(image, muscle, tumour, self.settings(p), progress=self._reporter(progress, "Segmentation"))
        self.writeResults(p, result)
        logging.info("BreastSegmentation: %s", self.summaryText(result))
        return self.summaryText(result)

    def _requireMuscle(self, parameterNode, image):
        muscle = self.segmentMask(parameterNode, "muscle", image)
        if muscle is None:
            raise ValueError("the output segmentation has no 'muscle' segment: segment the pectoral muscle "
                             "first (step 1), it delimits the breast")
        return muscle

    # -- outputs ---------------------------------------------------------------------------------

    PROBABILITY_ROLES = {"fat": "probabilityFat", "glandular": "probabilityGlandular", "muscle": "probabilityMuscle",
                         "tumour": "probabilityTumour", "skin": "probabilitySkin"}

    def _probabilityVolume(self, parameterNode, tissue: str, image) -> None:
        from BreastBiomechLib.mrml import image_to_volume_node

        role = self.PROBABILITY_ROLES[tissue]
        volume = parameterNode.reference("inputVolume")
        name = self.scene.GenerateUniqueName(f"{volume.GetName()}_p_{tissue}")
        node = image_to_volume_node(image, self.scene, name, node=parameterNode.reference(role))
        parameterNode.set_reference(role, node)

    def _writeStructure(self, parameterNode, tissue: str, structure) -> None:
        from BreastBiomechLib.mrml import mask_to_segment

        mask_to_segment(structure.mask, self.segmentationNode(parameterNode), tissue, self.scene)
        self._probabilityVolume(parameterNode, tissue, structure.probability)

    def writeResults(self, parameterNode, result) -> None:
        """The merged label map into the output segmentation (one segment per tissue, the label
        table's names and colours; made if none), a probability volume per tissue, the bias
        field volume and the volumes table. A second run refills the same nodes."""
        from BreastBiomechLib.mrml import columns_to_table_node, image_to_volume_node, labels_to_segmentation_node

        p = parameterNode
        node = self.segmentationNode(p)
        labels_to_segmentation_node(result.labels, self.scene, node.GetName(), node=node)
        for tissue, image in result.probabilities.items():
            self._probabilityVolume(p, tissue, image)
        volume = p.reference("inputVolume")
        p.set_reference("biasField", image_to_volume_node(
            result.bias_field, self.scene, self.scene.GenerateUniqueName(f"{volume.GetName()}_bias_field"),
            node=p.reference("biasField")))
        p.set_reference("volumesTable", columns_to_table_node(
            self.volumeColumns(result.summary), self.scene, self.scene.GenerateUniqueName("TissueVolumes"),
            node=p.reference("volumesTable")))

    @staticmethod
    def volumeColumns(summary: dict) -> dict:
        """Per tissue: volume (cm^3) and share of the breast (muscle: none, it is not breast)."""
        volumes = summary["tissue_volumes_cm3"]
        breast = summary["breast_volume_cm3"]
        names = list(volumes)
        return {"tissue": np.array(names, dtype=object),
                "volume (cm3)": np.array([volumes[n] for n in names]),
                "breast share (%)": np.array([np.nan if n == "muscle" or not breast else 100 * volumes[n] / breast
                                              for n in names])}

    @staticmethod
    def summaryText(result) -> str:
        s = result.summary
        em = s["em"]
        return (f"Breast {s['breast_volume_cm3']:.0f} cm³, glandular density {s['glandular_density']:.1%}. "
                f"EM: {em['iterations']} iterations ({'converged' if em['converged'] else 'not converged'}); "
                f"bias field {em['bias_range'][0]:.2f}-{em['bias_range'][1]:.2f}; "
                f"{sum(s['seconds'].values()):.1f} s.")

    @staticmethod
    def _volume_cm3(mask) -> float:
        import SimpleITK as sitk

        return float(np.count_nonzero(sitk.GetArrayViewFromImage(mask)) * np.prod(mask.GetSpacing()) / 1000.0)

    def showResults(self, parameterNode) -> None:
        """Show the MR volume with the segmentation over it in the slice views (application only)."""
        if not IN_SLICER_APPLICATION:
            return
        volume = parameterNode.reference("inputVolume")
        if volume is not None:
            slicer.util.setSliceViewerLayers(background=volume, fit=False)
        segmentation = parameterNode.reference("outputSegmentation")
        if segmentation is not None and segmentation.GetDisplayNode() is not None:
            segmentation.GetDisplayNode().SetVisibility(True)


#
# Test (runs inside Slicer: Reload and Test; the thorough checks run headless in Testing/)
#


class BreastSegmentationTest(ModuleTestMixin, ScriptedLoadableModuleTest):
    REQUIRES = tuple(DEPENDENCIES)

    def test_segment_phantom(self):
        from BreastBiomechLib.mrml import image_to_volume_node, landmarks_to_markups_node
        from BreastBiomechLib.phantom import PhantomParameters, generate_phantom
        from BreastBiomechLib.phantom.seeds import seed_points

        self.delayDisplay("Segmenting a 450 cm³ phantom with a tumour")
        case = generate_phantom(PhantomParameters(volume_cm3=450.0, tumour_diameter_mm=15.0))
        logic = BreastSegmentationLogic()
        p = logic.getParameterNode()
        p.set_reference("inputVolume", image_to_volume_node(case.image, slicer.mrmlScene, "MR"))
        p.set_reference("muscleSeeds", landmarks_to_markups_node(seed_points(case.labels, "muscle", 4),
                                                                 slicer.mrmlScene, "MuscleSeeds"))
        p.set_reference("tumourSeeds", landmarks_to_markups_node(seed_points(case.labels, "tumour", 3),
                                                                 slicer.mrmlScene, "TumourSeeds"))
        logic.runAll(p)
        segmentation = p.reference("outputSegmentation").GetSegmentation()
        self.assertEqual(segmentation.GetNumberOfSegments(), 4)
        logic.showResults(p)
        self.delayDisplay("Test passed")
