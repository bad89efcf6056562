"""BreastOptimization: fit tissue material parameters so that the FE-predicted compressed MR image
matches the measured one (seed section 2.4).

Choose the case (undeformed and measured compressed volumes, the fitting mesh, the landmarks
before and after compression and the measured plates, or load a compressed case folder), the
model variant and its free parameters, the optimiser and its budget; run, pause and resume
(every evaluation is kept in the output folder), or cancel and see the best so far. A live
convergence chart follows the run; at the end the predicted volume lies over the measured one
in the slice views, the landmark errors are a table and lines from predicted to measured
landmarks, and the fitted parameters are a table. The cohort study section fits the chosen model
variants to every compressed case of a folder (the seed's Tables 2 and 3) in Slicer, or sends
the fits to a Dask cluster by its scheduler's address, with progress and a table of the fits.

Module, Widget, Logic and Test classes follow Slicer's scripted-module template. The Logic holds
no Qt and runs headless on the ``slicer-core`` wheel (see docs/developing.md).
"""

from __future__ import annotations

import json
import logging

import numpy as np
import slicer
from BreastBiomechCommon import (IN_SLICER_APPLICATION, ModuleBase, ModuleLogicBase, ModuleTestMixin,
                                 ModuleWidgetBase, ScriptedLoadableModuleTest, _, chosen_folder, dependencies_ready,
                                 ensure_library_importable, resolve_device, show_path)

ensure_library_importable()

CASE_DEPENDENCIES = ["numpy", "scipy", "SimpleITK"]  # reading a compressed case into the scene
DEPENDENCIES = ["numpy", "scipy", "SimpleITK", "matplotlib", "warp", "cma"]  # fitting
EDGE_ATTRIBUTE = "BreastBiomech.PlateEdge"  # a measured plate's rounded edge (JSON, LPS mm), as in plates.json
NAME_ATTRIBUTE = "BreastBiomech.PlateName"  # its name in plates.json


class BreastOptimization(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent)
        self.parent.title = _("Breast Optimization")
        self.parent.helpText = _(
            "Fit the tissues' Young's moduli, Poisson's ratios and fibre stiffness so that the FE-predicted "
            "compressed MR image matches the measured one (maximum NMI), with the seed's hybrid search or "
            "CMA-ES, batched on the GPU. Pause and resume lose nothing. Cohort study: the model variants fitted to "
            "every case of a folder, in Slicer or on a Dask cluster given by its scheduler address (docs/cohorts.md). "
            "See docs/optimisation.md of the "
            "<a href='https://github.com/BreastBiomech/BreastBiomech'>project</a>."
        )
        self.parent.acknowledgementText = _("Method after Han et al. 2012, Phys. Med. Biol. 57:455, section 2.4.")


class BreastOptimizationWidget(ModuleWidgetBase):
    """Thin GUI: reads and writes the parameter node, calls the Logic, shows the result."""

    UI_FILE = "UI/BreastOptimization.ui"

    def __init__(self, parent=None):
        ModuleWidgetBase.__init__(self, parent)
        self._stopRequest = None  # None, "pause" or "cancel"

    def createLogic(self):
        return BreastOptimizationLogic()

    def connectGUI(self):
        for selector in (self.ui.undeformedVolumeSelector, self.ui.measuredVolumeSelector, self.ui.inputMeshSelector,
                         self.ui.referenceLandmarksSelector, self.ui.measuredLandmarksSelector):
            selector.currentNodeChanged.connect(self.updateParameterNodeFromGUI)
        for comboBox in (self.ui.modelComboBox, self.ui.optimiserComboBox, self.ui.objectiveComboBox,
                         self.ui.deviceComboBox):
            comboBox.currentIndexChanged.connect(self.updateParameterNodeFromGUI)
        for checkBox in (self.ui.freeECheckBox, self.ui.freeNuCheckBox, self.ui.freeEtaCheckBox,
                         self.ui.freeFibreCheckBox, self.ui.freeOffsetCheckBox):
            checkBox.toggled.connect(self.updateParameterNodeFromGUI)
        for spinBox in (self.ui.budgetSpinBox, self.ui.secondsSpinBox, self.ui.seedSpinBox,
                        self.ui.populationSpinBox, self.ui.binsSpinBox, self.ui.toleranceSpinBox,
                        self.ui.fibreRSpinBox, self.ui.fibreASpinBox, self.ui.fibreSSpinBox):
            spinBox.valueChanged.connect(self.updateParameterNodeFromGUI)
        self.ui.outputPathLineEdit.currentPathChanged.connect(self.updateParameterNodeFromGUI)
        self.ui.studyCasesPathLineEdit.currentPathChanged.connect(self.updateParameterNodeFromGUI)
        self.ui.studyOutputPathLineEdit.currentPathChanged.connect(self.updateParameterNodeFromGUI)
        self.ui.schedulerLineEdit.editingFinished.connect(self.updateParameterNodeFromGUI)
        self.ui.studyBudgetsLineEdit.editingFinished.connect(self.updateParameterNodeFromGUI)
        self.ui.studyEdgeSpinBox.valueChanged.connect(self.updateParameterNodeFromGUI)
        for checkBox in self._studyModelCheckBoxes().values():
            checkBox.toggled.connect(self.updateParameterNodeFromGUI)
        self.ui.runStudyButton.clicked.connect(self.onRunStudyButton)
        self.ui.cancelStudyButton.clicked.connect(lambda: self._requestStop("cancel"))
        self.ui.loadCaseButton.clicked.connect(self.onLoadCaseButton)
        self.ui.runButton.clicked.connect(lambda: self.onRunButton(resume=False))
        self.ui.resumeButton.clicked.connect(lambda: self.onRunButton(resume=True))
        self.ui.pauseButton.clicked.connect(lambda: self._requestStop("pause"))
        self.ui.cancelButton.clicked.connect(lambda: self._requestStop("cancel"))
        self._setRunning(False)

    def _studyModelCheckBoxes(self):
        return {"iso-homo": self.ui.studyIsoHomoCheckBox, "aniso-homo": self.ui.studyAnisoHomoCheckBox,
                "iso-hetero": self.ui.studyIsoHeteroCheckBox, "aniso-hetero": self.ui.studyAnisoHeteroCheckBox}

    @staticmethod
    def _setComboText(comboBox, text):
        comboBox.currentIndex = max(comboBox.findText(text), 0)

    def showParameters(self, p):
        for selector, role in ((self.ui.undeformedVolumeSelector, "undeformedVolume"),
                               (self.ui.measuredVolumeSelector, "measuredVolume"),
                               (self.ui.inputMeshSelector, "inputMesh"),
                               (self.ui.referenceLandmarksSelector, "referenceLandmarks"),
                               (self.ui.measuredLandmarksSelector, "measuredLandmarks")):
            selector.setCurrentNode(p.reference(role))
        for comboBox, name in ((self.ui.modelComboBox, "model"), (self.ui.optimiserComboBox, "optimiser"),
                               (self.ui.objectiveComboBox, "objective"), (self.ui.deviceComboBox, "device")):
            self._setComboText(comboBox, p[name])
        self.ui.freeECheckBox.checked = p["freeE"]
        self.ui.freeNuCheckBox.checked = p["freeNu"]
        self.ui.freeEtaCheckBox.checked = p["freeEta"]
        self.ui.freeEtaCheckBox.enabled = p["model"].startswith("aniso")
        self.ui.freeFibreCheckBox.checked = p["freeFibre"]
        self.ui.freeFibreCheckBox.enabled = p["model"].startswith("aniso")
        self.ui.freeOffsetCheckBox.checked = p["freeOffset"]
        for spinBox, name in ((self.ui.budgetSpinBox, "budget"), (self.ui.secondsSpinBox, "seconds"),
                              (self.ui.seedSpinBox, "seed"), (self.ui.populationSpinBox, "population"),
                              (self.ui.binsSpinBox, "bins"), (self.ui.toleranceSpinBox, "toleranceMm"),
                              (self.ui.fibreRSpinBox, "fibreR"), (self.ui.fibreASpinBox, "fibreA"),
                              (self.ui.fibreSSpinBox, "fibreS")):
            spinBox.value = p[name]
        show_path(self.ui.outputPathLineEdit, p["outputDirectory"])
        show_path(self.ui.studyCasesPathLineEdit, p["studyCasesDirectory"])
        show_path(self.ui.studyOutputPathLineEdit, p["studyOutputDirectory"])
        self.ui.schedulerLineEdit.text = p["scheduler"]
        self.ui.studyBudgetsLineEdit.text = p["studyBudgets"]
        self.ui.studyEdgeSpinBox.value = p["studyEdgeMm"]
        chosen = {m.strip() for m in p["studyModels"].split(",")}
        for model, checkBox in self._studyModelCheckBoxes().items():
            checkBox.checked = model in chosen
        self.ui.studyTableView.setMRMLTableNode(p.reference("studyTable"))
        plates = p.references("plates")
        self.ui.platesLabel.text = ", ".join(n.GetName() for n in plates) if plates else "none: load a case"
        self.ui.landmarkErrorsTableView.setMRMLTableNode(p.reference("landmarkErrorsTable"))
        self.ui.parametersTableView.setMRMLTableNode(p.reference("parametersTable"))

    def storeParameters(self, p):
        p.set_reference("undeformedVolume", self.ui.undeformedVolumeSelector.currentNode())
        p.set_reference("measuredVolume", self.ui.measuredVolumeSelector.currentNode())
        p.set_reference("inputMesh", self.ui.inputMeshSelector.currentNode())
        p.set_reference("referenceLandmarks", self.ui.referenceLandmarksSelector.currentNode())
        p.set_reference("measuredLandmarks", self.ui.measuredLandmarksSelector.currentNode())
        p["model"] = self.ui.modelComboBox.currentText
        p["optimiser"] = self.ui.optimiserComboBox.currentText
        p["objective"] = self.ui.objectiveComboBox.currentText
        p["device"] = self.ui.deviceComboBox.currentText
        p["freeE"] = self.ui.freeECheckBox.checked
        p["freeNu"] = self.ui.freeNuCheckBox.checked
        p["freeEta"] = self.ui.freeEtaCheckBox.checked
        p["freeFibre"] = self.ui.freeFibreCheckBox.checked
        p["freeOffset"] = self.ui.freeOffsetCheckBox.checked
        p["budget"] = int(self.ui.budgetSpinBox.value)
        p["seconds"] = self.ui.secondsSpinBox.value
        p["seed"] = int(self.ui.seedSpinBox.value)
        p["population"] = int(self.ui.populationSpinBox.value)
        p["bins"] = int(self.ui.binsSpinBox.value)
        p["toleranceMm"] = self.ui.toleranceSpinBox.value
        p["fibreR"] = self.ui.fibreRSpinBox.value
        p["fibreA"] = self.ui.fibreASpinBox.value
        p["fibreS"] = self.ui.fibreSSpinBox.value
        p["outputDirectory"] = self.ui.outputPathLineEdit.currentPath
        p["studyCasesDirectory"] = self.ui.studyCasesPathLineEdit.currentPath
        p["studyOutputDirectory"] = self.ui.studyOutputPathLineEdit.currentPath
        p["scheduler"] = self.ui.schedulerLineEdit.text.strip()
        p["studyBudgets"] = self.ui.studyBudgetsLineEdit.text.strip()
        p["studyEdgeMm"] = self.ui.studyEdgeSpinBox.value
        p["studyModels"] = ",".join(m for m, box in self._studyModelCheckBoxes().items() if box.checked)

    def onLoadCaseButton(self):
        if not dependencies_ready(CASE_DEPENDENCIES, _("Breast Optimization")):
            return
        folder = self.ui.casePathLineEdit.currentPath
        with slicer.util.tryWithErrorDisplay(_("Failed to load the compressed case."), waitCursor=True):
            self.logic.loadCompressedCase(self._parameterNode, folder)
            self.logic.showComparison(self._parameterNode)

    def onRunStudyButton(self):
        if not dependencies_ready(DEPENDENCIES + ["distributed"], _("Breast Optimization")):
            return
        self._stopRequest = None
        self._setRunning(True)
        self.ui.studyProgressBar.value = 0

        def report(state):
            self.ui.studyProgressBar.value = int(100 * state.done / max(state.total, 1))
            self.ui.studyProgressBar.setFormat(f"{state.done}/{state.total} tasks")
            self.ui.studyStatusLabel.text = "\n".join(f"{label}: {line}" for label, line in sorted(state.running.items()))
            slicer.app.processEvents()
            return self._stopRequest is None

        from BreastBiomechLib.cohort import CohortCancelled

        try:
            with slicer.util.tryWithErrorDisplay(_("Study failed."), waitCursor=True):
                try:
                    run = self.logic.runStudy(self._parameterNode, progress=report)
                except CohortCancelled as cancelled:
                    self.ui.studyStatusLabel.text = f"{cancelled}: Run study continues it"
                else:
                    self.ui.studyStatusLabel.text = (f"{len(run.rows)} fits in the study folder" + "".join(
                        f"\nFAILED {o.label}: {o.error}" for o in run.failed))
        finally:
            self._setRunning(False)

    def _requestStop(self, what):
        self._stopRequest = what

    def _setRunning(self, running):
        self.ui.runButton.enabled = not running
        self.ui.resumeButton.enabled = not running
        self.ui.pauseButton.enabled = running
        self.ui.cancelButton.enabled = running
        self.ui.runStudyButton.enabled = not running
        self.ui.cancelStudyButton.enabled = running

    def onRunButton(self, resume):
        if not dependencies_ready(DEPENDENCIES, _("Breast Optimization")):
            return
        self._stopRequest = None
        self._setRunning(True)
        self.ui.progressBar.value = 0

        def report(done, budget, best, phase):
            self.ui.progressBar.value = int(100 * done / max(budget, 1))
            self.ui.progressBar.setFormat(f"{done}/{budget} solves ({phase}), best {best:.4f}")
            slicer.app.processEvents()
            return self._stopRequest is None

        try:
            with slicer.util.tryWithErrorDisplay(_("Optimisation failed."), waitCursor=True):
                outcome = self.logic.run(self._parameterNode, progress=report, resume=resume,
                                         showBest=lambda: self._stopRequest != "pause")
                self.ui.statusLabel.text = outcome["summary"]
                if outcome["result"].stopped != "cancelled" or self._stopRequest == "cancel":
                    self.logic.showComparison(self._parameterNode)
        finally:
            self._setRunning(False)


class BreastOptimizationLogic(ModuleLogicBase):
    """A compressed case from MRML nodes into a :class:`~BreastBiomechLib.optimisation.FittingProblem`,
    the optimisation, and its results back as nodes. No Qt: runs in Slicer and headless.

    Frames: the nodes hold RAS; the library LPS (``BreastBiomechLib.mrml`` converts). The fibre
    direction parameters are RAS components. Moduli in Pa."""

    MODULE_NAME = "BreastOptimization"
    DEFAULTS = {"model": "aniso-hetero", "freeE": True, "freeNu": True, "freeEta": True, "freeFibre": False,
                "freeOffset": False,
                "fibreR": 0.0, "fibreA": 0.0, "fibreS": 1.0, "optimiser": "cmaes", "budget": 200, "seconds": 0.0,
                "seed": 0, "population": 0, "objective": "nmi", "bins": 64, "toleranceMm": 0.01, "device": "auto",
                "outputDirectory": "", "caseDirectory": "", "studyCasesDirectory": "", "studyOutputDirectory": "",
                "studyModels": "iso-homo,aniso-homo,iso-hetero,aniso-hetero", "studyBudgets": "", "studyEdgeMm": 4.0,
                "scheduler": ""}
    ROLES = ("undeformedVolume", "measuredVolume", "inputMesh", "referenceLandmarks", "measuredLandmarks", "plates",
             "predictedVolume", "predictedLandmarks", "errorLines", "landmarkErrorsTable", "parametersTable",
             "convergenceTable", "convergenceChart", "studyTable")

    # -- inputs ----------------------------------------------------------------------------------

    def loadCompressedCase(self, parameterNode, caseDir, meshPath=None) -> None:
        """Load a compressed case folder (``breastbiomech phantom --compressed``: the undeformed MR
        and landmarks, the measured compressed MR, landmarks and final plates) into the scene and
        choose its nodes; ``meshPath``: a fitting mesh (.vtu) to load too."""
        from pathlib import Path

        from BreastBiomechLib.io.images import read_image
        from BreastBiomechLib.io.markups import read_markups
        from BreastBiomechLib.mrml import image_to_volume_node, landmarks_to_markups_node
        from BreastBiomechLib.phantom.compressed_files import read_compressed

        folder = Path(chosen_folder(caseDir, "the case folder (it holds mr.nrrd and compressed/)"))
        measured = read_compressed(folder)
        if not (folder / "mr.nrrd").is_file():
            raise FileNotFoundError(f"{folder}: no undeformed mr.nrrd beside compressed/")
        p = parameterNode
        p.set_reference("undeformedVolume", image_to_volume_node(read_image(folder / "mr.nrrd"), self.scene,
                                                                 "Undeformed MR"))
        p.set_reference("measuredVolume", image_to_volume_node(measured.image, self.scene, "Measured compressed MR"))
        if (folder / "landmarks.mrk.json").is_file():
            p.set_reference("referenceLandmarks", landmarks_to_markups_node(
                read_markups(folder / "landmarks.mrk.json"), self.scene, "Reference landmarks"))
        p.set_reference("measuredLandmarks", landmarks_to_markups_node(measured.landmarks, self.scene,
                                                                       "Measured landmarks"))
        p.set_references("plates", [self._planeNode(plate) for plate in measured.plates])
        p["caseDirectory"] = str(folder)
        if meshPath:
            from BreastBiomechLib.io.meshes import read_vtu
            from BreastBiomechLib.mrml import tetmesh_to_model_node

            p.set_reference("inputMesh", tetmesh_to_model_node(read_vtu(meshPath), self.scene, "Fitting mesh"))

    def _planeNode(self, plate: dict):
        """A markups plane at a measured final plate (plates.json dict: name, point, normal LPS)."""
        from BreastBiomechLib.mrml import plate_to_plane_node
        from BreastBiomechLib.solver.model import Plate

        normal = np.asarray(plate["normal"], float)
        node = plate_to_plane_node(Plate(np.asarray(plate["point"], float), normal / np.linalg.norm(normal),
                                         np.zeros(3), [], plate.get("name", "plate")), self.scene)
        node.SetName(self.scene.GenerateUniqueName(f"Measured {plate.get('name', 'plate')} plate"))
        node.SetAttribute(NAME_ATTRIBUTE, plate.get("name", "plate"))
        if plate.get("edge"):
            node.SetAttribute(EDGE_ATTRIBUTE, json.dumps(plate["edge"]))
        return node

    @staticmethod
    def finalPlates(parameterNode, mesh) -> list[dict]:
        """The measured final plates as plates.json dicts (LPS mm; normals towards the mesh)."""
        from BreastBiomechLib.mrml import plate_from_plane_node

        planes = parameterNode.references("plates")
        if len(planes) < 1:
            raise ValueError("no measured plates: load a compressed case or add markups planes at the final plates")
        centre = mesh.nodes.mean(axis=0)
        plates = []
        for node in planes:
            plate = plate_from_plane_node(node, [], towards=centre)
            entry = {"name": node.GetAttribute(NAME_ATTRIBUTE) or plate.name, "point": (plate.point + plate.displacement).tolist(),
                     "normal": plate.normal.tolist()}
            if node.GetAttribute(EDGE_ATTRIBUTE):
                entry["edge"] = json.loads(node.GetAttribute(EDGE_ATTRIBUTE))
            plates.append(entry)
        return plates

    def _required(self, parameterNode, role: str, what: str):
        node = parameterNode.reference(role)
        if node is None:
            raise ValueError(f"choose the {what}")
        return node

    def fibre(self, parameterNode) -> tuple[float, float, float]:
        """The anisotropic models' fibre direction as a unit vector in LPS."""
        from BreastBiomechLib.mrml import frames

        ras = np.array([parameterNode["fibreR"], parameterNode["fibreA"], parameterNode["fibreS"]], float)
        if np.linalg.norm(ras) == 0:
            raise ValueError("the fibre direction must not be zero")
        return tuple(float(v) for v in frames.flip(ras / np.linalg.norm(ras)))

    def space(self, parameterNode, mesh):
        """The parameter space of the chosen model and free parameters on ``mesh``'s tissues (the
        fibre direction's angles, anisotropic models only, and the plates' offsets included
        where chosen)."""
        from BreastBiomechLib.optimisation import ParameterSpace

        free = tuple(name for name, key in (("E", "freeE"), ("nu", "freeNu"), ("eta", "freeEta"),
                                            ("fibre", "freeFibre"), ("offset", "freeOffset"))
                     if parameterNode[key])
        if "fibre" in free and not parameterNode["model"].startswith("aniso"):
            free = tuple(name for name in free if name != "fibre")  # the checkbox is disabled there
        if "tissue" not in mesh.cell_data:
            raise ValueError("the mesh has no cell array 'tissue' (make it with Breast Mesh)")
        tissues = np.unique(np.asarray(mesh.cell_data["tissue"]).astype(int))
        plates = len(parameterNode.references("plates")) if "offset" in free else 0
        return ParameterSpace.for_model(parameterNode["model"], tissues, free=free, fibre=self.fibre(parameterNode),
                                        plates=plates)

    def problem(self, parameterNode):
        """The :class:`~BreastBiomechLib.optimisation.FittingProblem` of the chosen nodes."""
        from BreastBiomechLib.mrml import image_from_volume_node, landmarks_from_markups_node, tetmesh_from_model_node
        from BreastBiomechLib.optimisation import FittingProblem
        from BreastBiomechLib.solver import DynamicRelaxation

        p = parameterNode
        mesh = tetmesh_from_model_node(self._required(p, "inputMesh", "fitting mesh (a model node with tets)"))
        undeformed = image_from_volume_node(self._required(p, "undeformedVolume", "undeformed MR volume"))
        measured = image_from_volume_node(self._required(p, "measuredVolume", "measured compressed MR volume"))
        reference, moved = p.reference("referenceLandmarks"), p.reference("measuredLandmarks")
        landmarks = None
        if reference is not None and moved is not None:
            landmarks = (landmarks_from_markups_node(reference), landmarks_from_markups_node(moved))
        elif "landmarks" in p["objective"]:
            raise ValueError(f"the objective {p['objective']!r} needs the reference and measured landmarks")
        return FittingProblem(self.space(p, mesh), mesh, undeformed, measured, self.finalPlates(p, mesh),
                              landmarks=landmarks, objective=p["objective"], bins=p["bins"],
                              relaxation=DynamicRelaxation(tolerance_mm=p["toleranceMm"]),
                              device=self.resolveDevice(p["device"]))

    @staticmethod
    def resolveDevice(choice: str) -> str:
        """"cuda" or "cpu" for "auto" (the GPU when present), "cuda" or "cpu"."""
        return resolve_device(choice)

    # -- run -------------------------------------------------------------------------------------

    def run(self, parameterNode, progress=None, resume=False, showBest=True) -> dict:
        """Optimise, writing every evaluation to the output folder as it goes. The convergence
        table (best objective against forward solves) and its chart grow after every batch.
        ``progress(done, budget, best objective, phase)`` returning False stops the run: a later
        ``run(resume=True)`` continues it (the evaluations made are replayed, not solved again).
        A run that ends, or stops with ``showBest`` (a bool, or a function asked when it stops:
        pause or cancel), puts the results at the best parameters into the scene
        (:meth:`writeResults`). Returns {"result", "summary"}."""
        from BreastBiomechLib.mrml import frames
        from BreastBiomechLib.optimisation import optimise

        p = parameterNode
        output = chosen_folder(p["outputDirectory"], "an output folder: every evaluation is kept there, so a run "
                                                        "can be resumed")
        problem = self.problem(p)
        done, best = [], []

        def report(count, budget, objective, phase):
            done.append(count)
            best.append(objective)
            self._convergence(p, done, best)
            return None if progress is None else progress(count, budget, objective, phase)

        result = optimise(problem, p["optimiser"], p["budget"], p["seconds"] or None, p["seed"],
                          output, resume, report, population=p["population"] or None)
        summary = (f"{result.stopped}: best objective {result.best.objective:.5f} (NMI {result.best.nmi:.4f}) after "
                   f"{len(result.evaluations)} solves ({result.replayed} replayed, "
                   f"{sum(result.failures.values())} failed"
                   + "".join(f"; {count} {status}" for status, count in result.failures.items())
                   + f"), {result.seconds:.0f} s")
        if "fibre" in result.geometry:
            ras = frames.flip(np.asarray(result.geometry["fibre"]))
            summary += "\nfitted fibre direction (RAS): " + " ".join(f"{v:.3f}" for v in ras)
        if "plate_offsets_mm" in result.geometry:
            summary += "\nfitted plate offsets (mm, towards the tissue): " + ", ".join(
                f"{node.GetName()} {offset:+.2f}" for node, offset in
                zip(p.references("plates"), result.geometry["plate_offsets_mm"]))
        if result.stopped == "cancelled" and not (showBest() if callable(showBest) else showBest):
            summary += "; paused: Resume continues"
        else:
            summary += "\n" + self.writeResults(p, problem, result)
        logging.info("BreastOptimization: %s", summary)
        return {"result": result, "summary": summary}

    def _convergence(self, parameterNode, done, best) -> None:
        from BreastBiomechLib.mrml import columns_to_table_node, plot_chart_node

        p = parameterNode
        columns = {"forward solves": np.array(done, float), "best objective": np.array(best, float)}
        table = columns_to_table_node(columns, self.scene, "Optimisation convergence",
                                      node=p.reference("convergenceTable"))
        p.set_reference("convergenceTable", table)
        p.set_reference("convergenceChart", plot_chart_node(
            table, "forward solves", ["best objective"], self.scene, "Optimisation convergence",
            "objective (-NMI)" if p["objective"] == "nmi" else "objective", node=p.reference("convergenceChart")))

    def writeResults(self, parameterNode, problem, result) -> str:
        """The results at the best parameters as nodes: the predicted compressed volume (on the
        measured grid), the fitted parameters table, and with landmarks the predicted landmarks,
        the landmark errors table (mm) and the error lines (predicted to measured, coloured by
        error). The output folder becomes a complete fit folder, as ``breastbiomech optimise``
        writes it (the fitting mesh, its solution, the predicted image, and the case folder when
        the case was loaded with :meth:`loadCompressedCase`), which Breast Discrepancy diagnoses.
        Returns a line summarising the landmark errors."""
        import json
        from pathlib import Path

        from BreastBiomechLib.io.images import write_image
        from BreastBiomechLib.io.meshes import write_vtu
        from BreastBiomechLib.landmarks import landmark_errors, map_landmarks
        from BreastBiomechLib.mesh.tetmesh import TetMesh
        from BreastBiomechLib.mrml import (columns_to_table_node, image_to_volume_node,
                                           landmarks_from_markups_node, landmarks_to_markups_node)
        from BreastBiomechLib.optimisation.run import solve_best

        p = parameterNode
        out, mesh = Path(p["outputDirectory"]), problem.mesh
        result, best = solve_best(problem, result, out)
        write_vtu(out / "fitting_mesh.vtu", mesh)
        write_vtu(out / "deformed_mesh.vtu", TetMesh(mesh.nodes, mesh.tets, {**mesh.point_data,
                                                                              "displacement": best.displacement},
                                                     dict(mesh.cell_data)))
        predicted = problem.predict(best.displacement).image
        write_image(out / "predicted.nrrd", predicted)
        if p["caseDirectory"]:
            from BreastBiomechLib.phantom.compressed_files import case_fingerprint

            (out / "case.json").write_text(json.dumps({"case_dir": p["caseDirectory"],
                                                       "fingerprint": case_fingerprint(p["caseDirectory"])}, indent=2)
                                           + "\n")
        p.set_reference("predictedVolume", image_to_volume_node(
            predicted, self.scene, "Predicted compressed MR",
            node=p.reference("predictedVolume")))
        names = list(result.materials)
        p.set_reference("parametersTable", columns_to_table_node(
            {"material": np.array(names), "E (Pa)": np.array([result.materials[n]["E"] for n in names]),
             "nu": np.array([result.materials[n]["nu"] for n in names]),
             "eta (Pa)": np.array([result.materials[n]["eta"] for n in names])},
            self.scene, "Fitted parameters", node=p.reference("parametersTable")))
        reference, moved = p.reference("referenceLandmarks"), p.reference("measuredLandmarks")
        if reference is None or moved is None:
            return "no landmarks chosen: no landmark errors"
        reference, measured = landmarks_from_markups_node(reference), landmarks_from_markups_node(moved)
        predicted = map_landmarks(problem.mesh, best.displacement, reference)
        p.set_reference("predictedLandmarks", landmarks_to_markups_node(
            predicted, self.scene, "Predicted landmarks", node=p.reference("predictedLandmarks")))
        errors = landmark_errors(reference, predicted, measured)
        p.set_reference("landmarkErrorsTable", columns_to_table_node(
            {"landmark": np.array(errors.labels), "displacement (mm)": errors.displacement_mm,
             "error (mm)": errors.error_mm}, self.scene, "Landmark errors", node=p.reference("landmarkErrorsTable")))
        p.set_reference("errorLines", self._errorLines(p, predicted, measured, errors))
        s = errors.summary()["error_mm"]
        return f"landmark error {s['mean']:.2f} ± {s['sd']:.2f} mm (max {s['max']:.2f}) over {len(errors.labels)} landmarks"

    def _errorLines(self, parameterNode, predicted, measured, errors):
        """A model of one line per landmark from its predicted to its measured position, with the
        cell array ``error_mm`` shown in colour."""
        from BreastBiomechLib.mrml.overlays import segments_to_model_node

        starts = np.array([predicted.position(label) for label in errors.labels], float)
        ends = np.array([measured.position(label) for label in errors.labels], float)
        return segments_to_model_node(starts, ends, errors.error_mm, "error_mm", self.scene, "Landmark errors",
                                      node=parameterNode.reference("errorLines"))

    # -- cohort study --------------------------------------------------------------------------

    def studyCases(self, parameterNode) -> list:
        """The compressed case folders of the study: the subfolders of the cases folder that hold
        a compressed/ part, in name order."""
        from pathlib import Path

        folder = Path(chosen_folder(parameterNode["studyCasesDirectory"],
                                        "a cases folder (its subfolders holding compressed/ are the cases)"))
        if not folder.is_dir():
            raise FileNotFoundError(f"the cases folder {folder} does not exist")
        cases = sorted(p for p in folder.iterdir() if (p / "compressed").is_dir())
        if not cases:
            raise ValueError(f"{folder} holds no compressed case (a subfolder with compressed/, as "
                             "`breastbiomech table1-cases` makes)")
        return cases

    def studyPlacement(self, parameterNode):
        """Where the study's fits run: the Dask cluster at the "scheduler" address, else this
        process (local worker processes are not started from inside Slicer: Slicer's
        ``sys.executable`` launcher cannot start them, Slicer/Slicer#7445; start a local cluster
        with `dask scheduler` and `dask worker` or run `breastbiomech study` outside Slicer)."""
        from BreastBiomechLib.cohort import place

        p = parameterNode
        if p["scheduler"].strip():
            return place(p["scheduler"].strip(), None, self.resolveDevice(p["device"]))
        return place(None, 0, self.resolveDevice(p["device"]))

    def runStudy(self, parameterNode, progress=None):
        """The four-model study (:func:`BreastBiomechLib.optimisation.study.run_study`) of the
        cases folder's compressed cases with the models of "studyModels" (comma-separated), their
        forward-solve budgets ("studyBudgets": MODEL=SOLVES items; the others keep the study's
        defaults), fitting meshes of "studyEdgeMm" (mm), and this panel's optimiser, seed, bins,
        tolerance and fibre direction, written to the study output
        folder (a rerun resumes), its fits run where :meth:`studyPlacement` says.
        ``progress(CohortProgress)`` returning False cancels. The rows go to the study table node
        (landmark errors in mm). Returns the :class:`~BreastBiomechLib.optimisation.study.StudyRun`."""
        from BreastBiomechLib.optimisation.study import DEFAULT_BUDGETS, StudySettings, run_study

        p = parameterNode
        cases = self.studyCases(p)
        output = chosen_folder(p["studyOutputDirectory"], "a study output folder (finished fits are kept there "
                                                             "and a rerun resumes)")
        models = tuple(m.strip() for m in p["studyModels"].split(",") if m.strip())
        budgets = dict(DEFAULT_BUDGETS)
        for item in p["studyBudgets"].replace(",", " ").split():
            model, _, count = item.partition("=")
            if model not in DEFAULT_BUDGETS or not count.isdigit():
                raise ValueError(f"budgets are MODEL=SOLVES with MODEL one of {tuple(DEFAULT_BUDGETS)}, not {item!r}")
            budgets[model] = int(count)
        settings = StudySettings(models=models, optimisers=(p["optimiser"],), budgets=budgets, fibre=self.fibre(p),
                                 edge_mm=p["studyEdgeMm"], seed=p["seed"], bins=p["bins"], tolerance_mm=p["toleranceMm"])
        run = run_study(cases, output, settings, placement=self.studyPlacement(p), progress=progress)
        self.studyTable(p, run.rows)
        logging.info("BreastOptimization: study of %d cases in %s: %d fits, %d failed tasks", len(cases), output,
                     len(run.rows), len(run.failed))
        return run

    def studyTable(self, parameterNode, rows) -> None:
        """The study's rows as the study table node: case, model, optimiser, NMI, landmark error
        mean and max (mm), forward solves, why the fit stopped, the device that solved it."""
        from BreastBiomechLib.mrml import columns_to_table_node

        def error(row, key):
            return row.landmark_errors["error_mm"][key] if row.landmark_errors else float("nan")

        columns = {"case": np.array([r.case for r in rows], dtype=object),
                   "model": np.array([r.model for r in rows], dtype=object),
                   "optimiser": np.array([r.optimiser for r in rows], dtype=object),
                   "NMI": np.array([r.nmi for r in rows], float),
                   "landmark error mean (mm)": np.array([error(r, "mean") for r in rows], float),
                   "landmark error max (mm)": np.array([error(r, "max") for r in rows], float),
                   "solves": np.array([r.evaluations for r in rows], float),
                   "stopped": np.array([r.stopped for r in rows], dtype=object),
                   "device": np.array([r.device for r in rows], dtype=object)}
        p = parameterNode
        p.set_reference("studyTable", columns_to_table_node(columns, self.scene, "Study fits",
                                                            node=p.reference("studyTable")))

    def showComparison(self, parameterNode) -> None:
        """Slice views: the measured volume with the predicted one faded over it (application
        only); the convergence chart in the layout."""
        if not IN_SLICER_APPLICATION:
            return
        p = parameterNode
        measured, predicted = p.reference("measuredVolume"), p.reference("predictedVolume")
        if measured is not None:
            slicer.util.setSliceViewerLayers(background=measured, foreground=predicted,
                                             foregroundOpacity=0.5 if predicted is not None else 0.0, fit=True)
        if p.reference("convergenceChart") is not None:
            slicer.modules.plots.logic().ShowChartInLayout(p.reference("convergenceChart"))


#
# Test (runs inside Slicer: Reload and Test; the thorough checks run headless in Testing/)
#


class BreastOptimizationTest(ModuleTestMixin, ScriptedLoadableModuleTest):
    REQUIRES = tuple(DEPENDENCIES + ["tetgen"])

    def test_fit_a_small_compressed_phantom(self):
        import tempfile

        from BreastBiomechLib.cli import main
        from BreastBiomechLib.io.images import read_image
        from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
        from BreastBiomechLib.mrml import tetmesh_to_model_node

        self.delayDisplay("Making a small compressed phantom and fitting the glandular modulus (3 solves)")
        folder = tempfile.mkdtemp()
        case = f"{folder}/case"
        main(["phantom", "--seed", "2", "--volume-cm3", "450", "--spacing", "1.5", "1.5", "3", "--compressed",
              "--compression", "0.25", "--truth-edge-mm", "6", "--no-overview", "--out", case])
        logic = BreastOptimizationLogic()
        p = logic.getParameterNode()
        logic.loadCompressedCase(p, case)
        mesh = mesh_labels(read_image(f"{case}/labels.nrrd"), MeshSettings(edge_mm=10.0, refine_interfaces=False)).mesh
        p.set_reference("inputMesh", tetmesh_to_model_node(mesh, slicer.mrmlScene, "Fitting mesh"))
        p["model"], p["freeNu"], p["budget"], p["outputDirectory"] = "iso-hetero", False, 3, f"{folder}/fit"
        outcome = logic.run(p)
        self.assertEqual(len(outcome["result"].evaluations), 3)
        self.assertIsNotNone(p.reference("predictedVolume"))
        logic.showComparison(p)
        self.delayDisplay("Test passed")
