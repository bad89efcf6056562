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
import os

import numpy as np
import slicer
from BreastBiomechCommon import (IN_SLICER_APPLICATION, ModuleBase, ModuleLogicBase, ModuleTestMixin,
                                 ModuleWidgetBase, ScriptedLoadableModuleTest, _, chosen_folder, dependencies_ready,
                                 ensure_library_importable, resolve_device)

ensure_library_importable()

CASE_DEPENDENCIES = ["numpy", "scipy", "SimpleITK"]  # reading a compressed case into the scene
DEPENDENCIES = ["numpy", "scipy", "SimpleITK", "matplotlib", "warp", "cma"]  # fitting
EDGE_ATTRIBUTE = "BreastBiomech.PlateEdge"  # a measured plate's rounded edge (JSON, LPS mm), as in plates.json
NAME_ATTRIBUTE = "BreastBiomech.PlateName"  # its name in plates.json
STATE_ATTRIBUTE = "BreastOptimization.State"  # a further measured state's name (the case folder's states/<name>)


class BreastOptimization(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent)
        self.parent.title = _("Breast Optimization")
        self.parent.helpText = _("""
Fit the tissues' Young's moduli, Poisson's ratios and fibre stiffness so that the FE-predicted
compressed MR image matches the measured one (maximum NMI), with the seed's hybrid search or CMA-ES,
batched on the GPU. Pause and resume lose nothing. Cohort study: the model variants fitted to every case
of a folder, in Slicer or on a Dask cluster given by its scheduler address (docs/cohorts.md). See
docs/optimisation.md of the <a href='https://github.com/BreastBiomech/BreastBiomech'>project</a>.
""")
        self.parent.acknowledgementText = _("""
Method after Han et al. 2012, Phys. Med. Biol. 57:455, section 2.4.
""")


class BreastOptimizationWidget(ModuleWidgetBase):
    def __init__(self, parent=None):
        ModuleWidgetBase.__init__(self, parent)
        self._stopRequest = None  # the study's: None or "cancel"

    def connectGUI(self):
        for checkBox in self._studyModelCheckBoxes().values():
            checkBox.toggled.connect(self.updateParameterNodeFromGUI)
        self.ui.cancelStudyButton.clicked.connect(lambda: self._requestStop("cancel"))
        self.ui.runButton.clicked.connect(lambda: self.startFit(resume=False))
        self.ui.resumeButton.clicked.connect(lambda: self.startFit(resume=True))
        self.ui.pauseButton.clicked.connect(self.onStopFit)
        self.ui.cancelButton.clicked.connect(self.onStopFit)
        self._setRunning(False)

    def _studyModelCheckBoxes(self):
        return {"iso-homo": self.ui.studyIsoHomoCheckBox, "aniso-homo": self.ui.studyAnisoHomoCheckBox,
                "iso-hetero": self.ui.studyIsoHeteroCheckBox, "aniso-hetero": self.ui.studyAnisoHeteroCheckBox}

    def showParameters(self, p):
        self.ui.freeEtaCheckBox.enabled = p["model"].startswith("aniso")
        self.ui.freeFibreCheckBox.enabled = p["model"].startswith("aniso")
        chosen = {m.strip() for m in p["studyModels"].split(",")}
        for model, checkBox in self._studyModelCheckBoxes().items():
            checkBox.checked = model in chosen
        self.ui.studyTableView.setMRMLTableNode(p.reference("studyTable"))
        plates = p.references("plates")
        self.ui.platesLabel.text = ", ".join(n.GetName() for n in plates) if plates else "none: load a case"
        self.ui.landmarkErrorsTableView.setMRMLTableNode(p.reference("landmarkErrorsTable"))
        self.ui.parametersTableView.setMRMLTableNode(p.reference("parametersTable"))

    def storeParameters(self, p):
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

    def startFit(self, resume):
        if not dependencies_ready(DEPENDENCIES, _("Breast Optimization")):
            return
        with slicer.util.tryWithErrorDisplay(_("Optimisation failed to start."), waitCursor=True):
            worker = self.logic.startRun(self._parameterNode, resume=resume)
            self._setRunning(True)
            self.ui.progressBar.value = 0
            self.ui.progressBar.setFormat(_("starting the fit"))
            self.startWorker(worker, self._fitEnded, self.ui.progressBar)

    def onStopFit(self):
        """Pause and Cancel: the fit's process is stopped; the solves it made are kept in the output
        folder and Resume goes on from them."""
        self.cancelWorker()

    def _fitEnded(self, worker):
        """The fit's process has ended (or was stopped): its results, or its convergence so far."""
        self._setRunning(False)
        with slicer.util.tryWithErrorDisplay(_("Optimisation failed."), waitCursor=True):
            parameterNode = self.logic.getParameterNode()  # also when the module was left meanwhile
            outcome = self.logic.finishRun(parameterNode, worker)
            self.ui.statusLabel.text = outcome["summary"]
            if outcome["record"] is not None:
                self.logic.showComparison(parameterNode)


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
             "convergenceTable", "convergenceChart", "studyTable", "stateVolumes", "statePredictedVolumes",
             "statesTable")

    # -- inputs ----------------------------------------------------------------------------------

    def loadCompressedCase(self, parameterNode, caseDir, meshPath=None) -> None:
        """Load a compressed case folder (``breastbiomech phantom --compressed``: the undeformed MR
        and landmarks, the measured compressed MR, landmarks and final plates) into the scene and
        choose its nodes; ``meshPath``: a fitting mesh (.vtu) to load too."""
        from pathlib import Path

        from BreastBiomechLib.io.case_layout import FIRST_STATE, CaseLayout
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
        if measured.landmarks is not None:
            p.set_reference("measuredLandmarks", landmarks_to_markups_node(measured.landmarks, self.scene,
                                                                           "Measured landmarks"))
        p.set_references("plates", [self._planeNode(plate) for plate in measured.plates])
        p.set_references("stateVolumes", [self._stateVolume(folder, name) for name in CaseLayout(folder).state_names()
                                          if name != FIRST_STATE])
        p["caseDirectory"] = str(folder)
        if meshPath:
            from BreastBiomechLib.io.meshes import read_vtu
            from BreastBiomechLib.mrml import tetmesh_to_model_node

            p.set_reference("inputMesh", tetmesh_to_model_node(read_vtu(meshPath), self.scene, "Fitting mesh"))

    def _stateVolume(self, folder, name: str):
        """A volume node of the measured image of the case folder's further state ``name``,
        tagged with its name (:data:`STATE_ATTRIBUTE`)."""
        from BreastBiomechLib.mrml import image_to_volume_node
        from BreastBiomechLib.phantom.compressed_files import read_compressed

        node = image_to_volume_node(read_compressed(folder, name).image, self.scene, f"Measured {name} MR")
        node.SetAttribute(STATE_ATTRIBUTE, name)
        return node

    def states(self, parameterNode) -> list[dict]:
        """The further measured states loaded with the case (:meth:`loadCompressedCase`), fitted
        jointly with the chosen nodes: each {"name", "measured" (image, from its volume node),
        "plates" and, where reference landmarks are chosen, "landmarks" (from the case folder's
        ``states/<name>/``), "folder"}. Refuses a state whose volume node lost its name or whose
        case folder is gone."""
        from pathlib import Path

        from BreastBiomechLib.io.case_layout import CaseLayout
        from BreastBiomechLib.mrml import image_from_volume_node
        from BreastBiomechLib.phantom.compressed_files import read_compressed

        p = parameterNode
        nodes = p.references("stateVolumes")
        if not nodes:
            return []
        if not p["caseDirectory"] or not Path(p["caseDirectory"]).is_dir():
            raise ValueError(f"the further measured states were loaded from {p['caseDirectory'] or 'a case folder'}, "
                             "which is gone: load the case again")
        out = []
        for node in nodes:
            name = node.GetAttribute(STATE_ATTRIBUTE)
            if not name:
                raise ValueError(f"{node.GetName()}: not a measured state's volume; load the case again")
            stored = read_compressed(p["caseDirectory"], name)
            landmarks = stored.landmarks if p.reference("referenceLandmarks") is not None else None
            out.append({"name": name, "measured": image_from_volume_node(node), "plates": stored.plates,
                        "landmarks": landmarks, "folder": CaseLayout(p["caseDirectory"]).state(name).folder})
        return out

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

    @staticmethod
    def freeParameters(parameterNode) -> tuple[str, ...]:
        """The free parameter names the checkboxes choose ("fibre" only for anisotropic models)."""
        free = tuple(name for name, key in (("E", "freeE"), ("nu", "freeNu"), ("eta", "freeEta"),
                                            ("fibre", "freeFibre"), ("offset", "freeOffset"))
                     if parameterNode[key])
        if "fibre" in free and not parameterNode["model"].startswith("aniso"):
            free = tuple(name for name in free if name != "fibre")  # the checkbox is disabled there
        return free

    def space(self, parameterNode, mesh):
        """The parameter space of the chosen model and free parameters on ``mesh``'s tissues (the
        fibre direction's angles, anisotropic models only, and the plates' offsets included
        where chosen)."""
        from BreastBiomechLib.optimisation import ParameterSpace

        free = self.freeParameters(parameterNode)
        if "tissue" not in mesh.cell_data:
            raise ValueError("the mesh has no cell array 'tissue' (make it with Breast Mesh)")
        tissues = np.unique(np.asarray(mesh.cell_data["tissue"]).astype(int))
        plates = len(parameterNode.references("plates")) if "offset" in free else 0
        return ParameterSpace.for_model(parameterNode["model"], tissues, free=free, fibre=self.fibre(parameterNode),
                                        plates=plates)

    def inputs(self, parameterNode) -> dict:
        """What a fit reads of the chosen nodes (LPS): the fitting ``mesh``, the ``undeformed`` and
        ``measured`` images, the ``landmarks`` (reference, measured; None without both) and the
        final ``plates``. Refuses a missing input, naming it."""
        from BreastBiomechLib.mrml import image_from_volume_node, landmarks_from_markups_node, tetmesh_from_model_node

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
        return {"mesh": mesh, "undeformed": undeformed, "measured": measured, "landmarks": landmarks,
                "plates": self.finalPlates(p, mesh)}

    def problem(self, parameterNode):
        """The :class:`~BreastBiomechLib.optimisation.FittingProblem` of the chosen nodes, or with
        further measured states loaded with the case the
        :class:`~BreastBiomechLib.optimisation.states.JointProblem` of them all."""
        from BreastBiomechLib.io.case_layout import FIRST_STATE
        from BreastBiomechLib.optimisation import FittingProblem
        from BreastBiomechLib.optimisation.states import JointProblem
        from BreastBiomechLib.solver import DynamicRelaxation

        p = parameterNode
        i = self.inputs(p)
        space, relaxation, device = (self.space(p, i["mesh"]), DynamicRelaxation(tolerance_mm=p["toleranceMm"]),
                                     self.resolveDevice(p["device"]))

        def state(measured, plates, landmarks):
            return FittingProblem(space, i["mesh"], i["undeformed"], measured, plates, landmarks=landmarks,
                                  objective=p["objective"], bins=p["bins"], relaxation=relaxation, device=device)

        first = state(i["measured"], i["plates"], i["landmarks"])
        further = self.states(p)
        if not further:
            return first
        reference = None if i["landmarks"] is None else i["landmarks"][0]
        return JointProblem({FIRST_STATE: first, **{
            s["name"]: state(s["measured"], s["plates"], None if reference is None else (reference, s["landmarks"]))
            for s in further}})

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
        summary = self.resultSummary(p, result.summary())
        if result.stopped == "cancelled" and not (showBest() if callable(showBest) else showBest):
            summary += "; paused: Resume continues"
        else:
            summary += "\n" + self.writeResults(p, problem, result)
        logging.info("BreastOptimization: %s", summary)
        return {"result": result, "summary": summary}

    # -- run out of Slicer's process -------------------------------------------------------------

    INPUTS = "inputs"  # the output folder's subfolder holding the fit's inputs as a case folder

    def writeInputs(self, parameterNode, folder) -> str:
        """The chosen nodes as a case folder (``folder``: mr.nrrd, compressed/ with the measured
        image and final plates, the landmarks where chosen;
        :func:`~BreastBiomechLib.phantom.compressed_files.write_measured_case`; the further
        measured states loaded with the case under states/) with the fitting mesh beside them
        (fitting_mesh.vtu): what `breastbiomech optimise` reads. Returns the folder."""
        from BreastBiomechLib.io.meshes import write_vtu
        from BreastBiomechLib.phantom.compressed_files import write_measured_case, write_measured_state

        i = self.inputs(parameterNode)
        self.space(parameterNode, i["mesh"])  # refuses bad choices before anything is written
        states = self.states(parameterNode)
        write_measured_case(folder, i["undeformed"], i["measured"], i["plates"], i["landmarks"])
        for state in states:
            write_measured_state(folder, state["name"], state["measured"],
                                 state["landmarks"] if i["landmarks"] is not None else None, state["folder"])
        write_vtu(os.path.join(str(folder), "fitting_mesh.vtu"), i["mesh"])
        return str(folder)

    def fitArguments(self, parameterNode, inputs: str, output: str, resume: bool) -> list[str]:
        """The `breastbiomech optimise` command line of the chosen settings."""
        p = parameterNode
        arguments = ["optimise", inputs, "--mesh", os.path.join(inputs, "fitting_mesh.vtu"), "--out", output,
                     "--model", p["model"], "--free", *self.freeParameters(p),
                     "--fibre", *[repr(v) for v in self.fibre(p)], "--optimiser", p["optimiser"],
                     "--budget", str(p["budget"]), "--seed", str(p["seed"]), "--objective", p["objective"],
                     "--bins", str(p["bins"]), "--tolerance-mm", repr(float(p["toleranceMm"]))]
        if not self.freeParameters(p):
            raise ValueError("choose at least one free parameter")
        if p["seconds"]:
            arguments += ["--seconds", repr(float(p["seconds"]))]
        if p["population"]:
            arguments += ["--population", str(p["population"])]
        if p["device"] != "auto":
            if p["device"] not in ("cuda", "cpu"):
                raise ValueError(f"device must be auto, cuda or cpu, not {p['device']!r}")
            arguments += ["--device", p["device"]]
        return arguments + (["--resume"] if resume else [])

    def startRun(self, parameterNode, resume=False):
        """Start the fit in a process of its own (`breastbiomech optimise`, see
        BreastBiomechCommon.worker): the chosen nodes written as a case folder in the output
        folder's ``inputs/`` (kept as they were when resuming, so a resumed fit goes on with the
        inputs it began with), every evaluation to the output folder as it goes. Returns the
        running :class:`~BreastBiomechCommon.worker.CommandWorker`; once it has ended,
        :meth:`finishRun` shows the results. Cancel (the worker's) keeps what was solved:
        ``startRun(resume=True)`` goes on from it."""
        from BreastBiomechCommon.worker import CommandWorker

        p = parameterNode
        output = chosen_folder(p["outputDirectory"], "an output folder: every evaluation is kept there, so a run "
                                                        "can be resumed")
        inputs = os.path.join(output, self.INPUTS)
        if resume and not os.path.isfile(os.path.join(inputs, "compressed", "plates.json")):
            raise ValueError(f"{output} holds no fit started from this panel to resume: press Run")
        if not resume:
            self.writeInputs(p, inputs)
        return CommandWorker(self.fitArguments(p, inputs, output, resume), folder=output).start()

    def finishRun(self, parameterNode, worker) -> dict:
        """The results of an ended :meth:`startRun` into the scene (:meth:`showFit` of its output
        folder); the convergence as it stood for a cancelled one (Resume continues it). Raises
        RuntimeError with the worker's reason where it failed. Returns {"summary", "record"}."""
        p = parameterNode
        if worker.running:
            raise RuntimeError("the fit is still running: wait for it or cancel it")
        if worker.cancelled:
            self._showEvaluations(p, worker.folder)
            return {"summary": "cancelled: the solves made are kept; Resume continues the fit", "record": None}
        if not worker.succeeded:
            raise RuntimeError(worker.error or "the fit wrote no results")
        line = self.showFit(p, worker.folder)
        with open(os.path.join(worker.folder, "result.json"), encoding="utf-8") as file:
            record = json.load(file)
        summary = self.resultSummary(p, record) + "\n" + line
        logging.info("BreastOptimization: %s", summary)
        return {"summary": summary, "record": record}

    def _showEvaluations(self, parameterNode, folder) -> None:
        """The convergence of the evaluations a fit folder holds so far."""
        from BreastBiomechLib.optimisation.record import read_evaluations

        path = os.path.join(str(folder), "evaluations.jsonl")
        if os.path.isfile(path):
            objectives = [e.objective if e.status == "completed" else np.inf for e in read_evaluations(path)]
            if objectives:
                self._convergence(parameterNode, list(range(1, len(objectives) + 1)),
                                  list(np.minimum.accumulate(objectives)))

    def resultSummary(self, parameterNode, record: dict) -> str:
        """The fit's outcome in a few lines, from its result.json ``record``."""
        from BreastBiomechLib.mrml import frames

        best = record["best"]
        summary = (f"{record['stopped']}: best objective {best['objective']:.5f} (NMI {best['nmi']:.4f}) after "
                   f"{record['evaluations']} solves ({record['replayed']} replayed, {record['failed']} failed"
                   + "".join(f"; {count} {status}" for status, count in record["failures"].items())
                   + f"), {record['seconds']:.0f} s")
        geometry = record.get("geometry", {})
        if "fibre" in geometry:
            ras = frames.flip(np.asarray(geometry["fibre"]))
            summary += "\nfitted fibre direction (RAS): " + " ".join(f"{v:.3f}" for v in ras)
        if "plate_offsets_mm" in geometry:
            summary += "\nfitted plate offsets (mm, towards the tissue): " + ", ".join(
                f"{node.GetName()} {offset:+.2f}" for node, offset in
                zip(parameterNode.references("plates"), geometry["plate_offsets_mm"]))
        return summary

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
        """The results at the best parameters written to the output folder as ``breastbiomech
        optimise`` writes them (a complete fit folder, which Breast Discrepancy diagnoses; with
        the case folder's record, and the absolute moduli its states' measured plate forces fix,
        when the case was loaded with :meth:`loadCompressedCase`), then shown (:meth:`showFit`).
        Returns a line summarising the landmark errors."""
        from pathlib import Path

        from BreastBiomechLib.io.case_layout import FIRST_STATE, CaseLayout, read_force
        from BreastBiomechLib.optimisation.case import write_fit_outputs

        p = parameterNode
        out = Path(p["outputDirectory"])
        names = getattr(problem, "states", None) or [FIRST_STATE]
        forces = {}
        if p["caseDirectory"]:  # the measured plate forces of the fitted states, where the case records them
            layout = CaseLayout(p["caseDirectory"])
            forces = {name: read_force(layout.state(name)) for name in names if layout.state(name).force.is_file()}
        write_fit_outputs(out, problem, result, forces)
        if p["caseDirectory"]:
            from BreastBiomechLib.optimisation.case import case_record

            (out / "case.json").write_text(json.dumps(case_record(p["caseDirectory"], names), indent=2) + "\n")
        return self.showFit(p, out)

    def showFit(self, parameterNode, folder) -> str:
        """A fit folder's results as nodes (what :func:`write_fit_outputs` wrote, read back: the
        same for a fit run in this process, out of it, or by ``breastbiomech optimise``): the
        predicted compressed volume (on the measured grid), the fitted parameters table, the
        convergence, and with landmarks the predicted landmarks, the landmark errors table (mm)
        and the error lines (predicted to measured, coloured by error; the measured landmarks
        those of the case the fit was made on). Returns a line summarising the landmark errors."""
        import json
        from pathlib import Path

        from BreastBiomechLib.io.images import read_image
        from BreastBiomechLib.io.markups import read_markups
        from BreastBiomechLib.landmarks import LandmarkErrors
        from BreastBiomechLib.mrml import columns_to_table_node, image_to_volume_node, landmarks_to_markups_node

        p, folder = parameterNode, Path(folder)
        for name in ("result.json", "predicted.nrrd", "evaluations.jsonl"):
            if not (folder / name).is_file():
                raise FileNotFoundError(f"{folder} holds no {name}: not a finished fit")
        record = json.loads((folder / "result.json").read_text())
        p.set_reference("predictedVolume", image_to_volume_node(
            read_image(folder / "predicted.nrrd"), self.scene, "Predicted compressed MR",
            node=p.reference("predictedVolume")))
        materials = record["materials"]
        names = list(materials)
        p.set_reference("parametersTable", columns_to_table_node(
            {"material": np.array(names), "E (Pa)": np.array([materials[n]["E"] for n in names]),
             "nu": np.array([materials[n]["nu"] for n in names]),
             "eta (Pa)": np.array([materials[n]["eta"] for n in names])},
            self.scene, "Fitted parameters", node=p.reference("parametersTable")))
        self._showEvaluations(p, folder)
        self._showStates(p, folder, record)
        errors_path = folder / "landmark_errors.json"
        if not errors_path.is_file():
            return "no landmarks chosen: no landmark errors"
        case = Path(json.loads((folder / "case.json").read_text())["case_dir"]) if (folder / "case.json").is_file() \
            else None
        measured_path = None if case is None else case / "compressed" / "landmarks.mrk.json"
        predicted = read_markups(folder / "predicted_landmarks.mrk.json")
        p.set_reference("predictedLandmarks", landmarks_to_markups_node(
            predicted, self.scene, "Predicted landmarks", node=p.reference("predictedLandmarks")))
        table = json.loads(errors_path.read_text())
        labels = list(table["per_landmark"])
        errors = LandmarkErrors(labels, np.array([table["per_landmark"][k]["displacement_mm"] for k in labels]),
                                np.array([table["per_landmark"][k]["error_mm"] for k in labels]))
        p.set_reference("landmarkErrorsTable", columns_to_table_node(
            {"landmark": np.array(errors.labels), "displacement (mm)": errors.displacement_mm,
             "error (mm)": errors.error_mm}, self.scene, "Landmark errors", node=p.reference("landmarkErrorsTable")))
        if measured_path is not None and measured_path.is_file():
            measured = read_markups(measured_path)
        elif p.reference("measuredLandmarks") is not None:  # a fit of nodes chosen by hand, in this process
            from BreastBiomechLib.mrml import landmarks_from_markups_node

            measured = landmarks_from_markups_node(p.reference("measuredLandmarks"))
        else:
            measured = None
        if measured is not None:
            p.set_reference("errorLines", self._errorLines(p, predicted, measured, errors))
        s = table["error_mm"]
        return f"landmark error {s['mean']:.2f} ± {s['sd']:.2f} mm (max {s['max']:.2f}) over {len(labels)} landmarks"

    def _showStates(self, parameterNode, folder, record: dict) -> None:
        """A joint fit's further measured states: each one's predicted volume (on its measured
        grid) and the states table (each state's objective, NMI and mean landmark error at the
        best parameters); both emptied for a fit of one state."""
        from BreastBiomechLib.io.case_layout import STATES
        from BreastBiomechLib.io.images import read_image
        from BreastBiomechLib.mrml import columns_to_table_node, image_to_volume_node

        p = parameterNode
        figures = record["best"].get("states") or {}
        old = {node.GetAttribute(STATE_ATTRIBUTE): node for node in p.references("statePredictedVolumes")}
        nodes = []
        for name in list(figures)[1:]:
            node = image_to_volume_node(read_image(folder / STATES / name / "predicted.nrrd"), self.scene,
                                        f"Predicted {name} MR", node=old.get(name))
            node.SetAttribute(STATE_ATTRIBUTE, name)
            nodes.append(node)
        p.set_references("statePredictedVolumes", nodes)
        if not figures:
            p.set_reference("statesTable", None)
            return
        names = list(figures)
        p.set_reference("statesTable", columns_to_table_node(
            {"state": np.array(names), "objective": np.array([figures[n]["objective"] for n in names]),
             "NMI": np.array([figures[n]["nmi"] for n in names]),
             "landmark error (mm)": np.array([figures[n]["landmark_mean_mm"] for n in names])},
            self.scene, "Fitted states", node=p.reference("statesTable")))

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
