"""BreastDiscrepancy: see where the fitted model and the measured compressed scan disagree, which
candidate physical effect explains it with what evidence, accept one, refit, and watch the gap
shrink (docs/discrepancy.md).

Choose a compressed case folder and a fit folder (``breastbiomech optimise``'s, or the Breast
Optimization result in the scene) and an output folder. *Diagnose* runs a round: the ranked
candidates go to a table, the residual displacement magnitude lies over the measured volume in
colour with a legend, the residual field can be shown as glyphs, the landmark residuals are
lines from predicted to measured positions, the model's skin is coloured by its signed distance
to the measured body, and the regions are segments. Selecting a candidate shows the residual it
predicts beside the measured one. *Refit with effect* adds the chosen candidate (warm start) with
progress and cancel; before/after plots and overlays follow. *Design next measurement* says, for
the candidates the last round could not tell apart, which further acquisition would (a table of
separations and a sentence each). Every round keeps its nodes in a subject-hierarchy folder;
*Save report* writes the Markdown report with the slice views.

Module, Widget, Logic and Test classes follow Slicer's scripted-module template. The Logic holds
no Qt and runs headless on the ``slicer-core`` wheel (see docs/developing.md).
"""

from __future__ import annotations

import logging
import os
import weakref
from pathlib import Path

import numpy as np
import slicer
from BreastBiomechCommon import (IN_SLICER_APPLICATION, ModuleBase, ModuleLogicBase, ModuleTestMixin,
                                 ModuleWidgetBase, ScriptedLoadableModuleTest, _, chosen_folder,
                                 dependencies_ready, ensure_library_importable, resolve_device)

ensure_library_importable()

DEPENDENCIES = ["numpy", "scipy", "SimpleITK", "matplotlib", "warp"]
ROUND_ATTRIBUTE = "BreastDiscrepancy.Round"  # the round a node belongs to
KIND_ATTRIBUTE = "BreastDiscrepancy.Kind"    # what it shows, e.g. "residual-before"
FOLDER_ATTRIBUTE = "BreastDiscrepancy.Folder"  # the output folder of its diagnosis
SHOWN_FROM_MM = 0.25                        # residual magnitude drawn transparent below this


class BreastDiscrepancy(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent, ("SubjectHierarchy", "ScreenCapture"))
        self.parent.title = _("Breast Discrepancy")
        self.parent.helpText = _("""
Find where a fitted breast model and the measured compressed scan disagree, which physical effect (plate
friction, gravity and the unloaded state, the chest wall holding the breast, skin, anisotropy,
heterogeneity, tumour stiffness, plate tilt or offset) is missing, with the evidence on the images;
accept it, refit and see the gap shrink. Each round stays in the scene. From the Python console: logic =
slicer.util.getModuleLogic('BreastDiscrepancy'), then logic.diagnose(p), logic.showCandidate(p, name),
logic.accept(p, name), logic.reject(p, name), logic.designNext(p), logic.saveReport(p). See docs/discrepancy.md of the
<a href='https://github.com/BreastBiomech/BreastBiomech'>project</a>.
""")
        self.parent.acknowledgementText = _("""
Builds on the method of Han et al. 2012, Phys. Med. Biol. 57:455.
""")


class BreastDiscrepancyWidget(ModuleWidgetBase):
    def connectGUI(self):
        self.connectLogic(self.ui.glyphsCheckBox.toggled, self.logic.setGlyphsVisible)
        self.connectLogic(self.ui.regionsCheckBox.toggled, self.logic.setRegionsVisible)
        self.connectLogic(self.ui.roundComboBox.currentIndexChanged, self.showChosenRound)
        self.ui.candidatesTableView.selectionModel().selectionChanged.connect(self.onCandidateSelected)
        self._setRunning(False)

    def showParameters(self, p):
        # the view options act on the scene when toggled (not stored from the panel)
        self.ui.glyphsCheckBox.checked = p["fieldGlyphs"]
        self.ui.regionsCheckBox.checked = p["showRegions"]
        self.ui.candidatesTableView.setMRMLTableNode(p.reference("candidatesTable"))
        rounds = self.logic.roundNumbers(p)
        self.ui.roundComboBox.clear()
        for number in rounds:
            self.ui.roundComboBox.addItem(_("Round {number}").format(number=number), number)
        if p["shownRound"] in rounds:
            self.ui.roundComboBox.currentIndex = rounds.index(p["shownRound"])
        self.ui.verdictLabel.text = self.logic.verdictText(p)
        self.ui.candidateLabel.text = p["candidate"] or _("none: select a row of the table")

    def _setRunning(self, running):
        """While a step runs (in its own process) only Cancel is live: the buttons, the folders and
        settings, the round selector, the table and the view options would change what the step
        reads or shows."""
        for widget in (self.ui.diagnoseButton, self.ui.acceptButton, self.ui.rejectButton, self.ui.designButton,
                       self.ui.saveReportButton,
                       self.ui.useOptimizationButton, self.ui.inputsCollapsibleButton,
                       self.ui.settingsCollapsibleButton, self.ui.resultsCollapsibleButton):
            widget.enabled = not running
        self.ui.cancelButton.enabled = running

    def onUseOptimizationButton(self):
        self.runAction(["numpy"], _("No Breast Optimization fit to use."), self.logic.useOptimizationFit)

    def onDiagnoseButton(self):
        if not dependencies_ready(DEPENDENCIES, _("Breast Discrepancy")):
            return
        self._startStep(_("Diagnosis failed to start."), lambda: self.logic.startDiagnosis(self._parameterNode),
                        _("Diagnosis failed."), self.logic.finishDiagnosis)

    def onAcceptButton(self):
        if not dependencies_ready(DEPENDENCIES, _("Breast Discrepancy")):
            return
        name = self._parameterNode["candidate"] or None
        self._startStep(_("Refit failed to start."), lambda: self.logic.startAccept(self._parameterNode, name),
                        _("Refit failed."), self.logic.finishAccept)

    def _startStep(self, startTitle, start, title, finish):
        """A long step in its own process (the worker): the panel disabled but Cancel, its progress
        in the status line; once it has ended, ``finish(parameterNode, worker)`` shows it."""
        with slicer.util.tryWithErrorDisplay(startTitle, waitCursor=True):
            worker = start()
            self._setRunning(True)
            self.ui.statusLabel.text = _("starting")

            def ended(worker):
                self._setRunning(False)
                if worker.cancelled:
                    self.ui.statusLabel.text = _("Cancelled: what had finished is kept in the output folder; the "
                                                 "round in the panel is as it was")
                    return
                with slicer.util.tryWithErrorDisplay(title, waitCursor=True):
                    parameterNode = self.logic.getParameterNode()  # also when the module was left meanwhile
                    finish(parameterNode, worker)
                    self.ui.statusLabel.text = self.logic.verdictText(parameterNode)
                    self.logic.showRound(parameterNode, parameterNode["shownRound"])

            self.startWorker(worker, ended, statusLabel=self.ui.statusLabel)

    def onDesignButton(self):
        if not dependencies_ready(DEPENDENCIES, _("Breast Discrepancy")):
            return
        self._startStep(_("Design failed to start."), lambda: self.logic.startDesign(self._parameterNode),
                        _("Design failed."), self.logic.finishDesign)

    def onRejectButton(self):
        name = self.runAction(DEPENDENCIES, _("Could not reject the candidate."),
                              lambda p: self.logic.reject(p, p["candidate"] or None))
        if name is not None:
            self.ui.statusLabel.text = _("{name} rejected: Diagnose runs the next round without it").format(name=name)

    def onCancelButton(self):
        self.cancelWorker()

    def onCandidateSelected(self, *args):
        rows = self.ui.candidatesTableView.selectionModel().selectedIndexes()
        if not rows:
            return
        with slicer.util.tryWithErrorDisplay(_("Could not show the candidate."), waitCursor=True):
            name = self.logic.candidateAtRow(self._parameterNode, rows[0].row())
            self.logic.showCandidate(self._parameterNode, name)

    def showChosenRound(self, parameterNode, index):
        number = self.ui.roundComboBox.itemData(index)
        if number is not None:
            with slicer.util.tryWithErrorDisplay(_("Could not show the round."), waitCursor=True):
                self.logic.showRound(parameterNode, int(number))

    def onSaveReportButton(self):
        path = self.runAction(DEPENDENCIES, _("Could not save the report."),
                              lambda p: self.logic.saveReport(p, capture=captureSliceViews))
        if path is not None:
            self.ui.statusLabel.text = _("report: {path}").format(path=path)


def captureSliceViews(path) -> None:
    """Save the application's visible slice views, side by side, as one PNG (the report's
    screenshot): not the whole layout, whose plots and 3D view are not slice views."""
    import tempfile

    import ScreenCapture

    from BreastBiomechLib.visualisation import side_by_side

    layout = slicer.app.layoutManager()
    capture = ScreenCapture.ScreenCaptureLogic()
    with tempfile.TemporaryDirectory() as folder:
        pictures = []
        for name in layout.sliceViewNames():
            widget = layout.sliceWidget(name)
            if widget is not None and widget.isVisible():
                pictures.append(os.path.join(folder, f"{name}.png"))
                capture.captureImageFromView(widget.sliceView(), pictures[-1])
        if not pictures:
            raise ValueError("no slice view is shown: choose a layout with slice views to capture them")
        side_by_side(pictures, path)


class BreastDiscrepancyLogic(ModuleLogicBase):
    """The diagnosis of a fitted compressed case as MRML nodes, one step at a time
    (:class:`~BreastBiomechLib.discrepancy.session.DiagnosisSession`): rounds, their evidence as
    overlays, tables and plots, the user's decisions. No Qt: runs in Slicer and headless.

    Frames: the nodes hold RAS; the library LPS (``BreastBiomechLib.mrml`` converts). Distances
    in mm. Each round's nodes live in the subject-hierarchy folder "Round N" under
    "Discrepancy <output folder's name>" and
    carry the attributes ``BreastDiscrepancy.Round``, ``.Kind`` and ``.Folder`` (the output folder)."""

    MODULE_NAME = "BreastDiscrepancy"
    DEFAULTS = {"caseDirectory": "", "fitDirectory": "", "outputDirectory": "", "effects": "", "refineIterations": 2,
                "maxRounds": 4, "landmarkSdMm": 0.5, "modelSdMm": 0.5, "measuredFloor": True, "alpha": 0.01,
                "device": "auto", "residualField": True, "fieldGlyphs": False, "showRegions": False, "shownRound": 0,
                "candidate": "", "designAcquisitions": ""}
    ROLES = ("measuredVolume", "candidatesTable", "residualVolume", "candidateVolume", "residualTransform",
             "landmarkLines", "skinModel", "regions", "landmarkErrorsTable", "landmarkErrorsChart", "measuresTable",
             "measuresChart", "histogramTable", "histogramChart", "designTable")

    def __init__(self, scene=None):
        ModuleLogicBase.__init__(self, scene)
        self.session = None   # the open DiagnosisSession
        self._surface = None  # the measured body's signed distance, made once per session
        self._key = None
        # File > Close Scene removes the session's nodes (the measured volume, the rounds): the
        # session goes with them, and the next step opens it again from its output folder. The
        # observer holds the Logic weakly: a Python callback that held it would close a cycle
        # (scene -> callback -> Logic -> scene) whose collection ran the callback inside the
        # garbage collector, on a half-freed Logic (a segmentation fault under pytest)
        logic = weakref.ref(self)

        def dropped(caller, event):
            alive = logic()
            if alive is not None:
                alive.dropSession()

        self._closeObserver = self.scene.AddObserver(self.scene.EndCloseEvent, dropped)

    def dropSession(self) -> None:
        """Forget the open session (its files stay in the output folder; the next step takes them up)."""
        self.session, self._key, self._surface = None, None, None

    # -- inputs ----------------------------------------------------------------------------------

    def useOptimizationFit(self, parameterNode) -> None:
        """Take the case and fit folders of the Breast Optimization result in the scene: its output
        folder, once a run has ended, and the case that fit was made on (the fit's case.json: the
        case folder loaded with Load case, or the inputs a fit run out of Slicer's process wrote)."""
        import json

        optimisation = self.scene.GetSingletonNode("BreastOptimization", "vtkMRMLScriptedModuleNode")
        case = (optimisation.GetParameter("caseDirectory") if optimisation is not None else "") or ""
        fit = (optimisation.GetParameter("outputDirectory") if optimisation is not None else "") or ""
        if not case and not fit:
            raise ValueError("Breast Optimization has no case folder: load a compressed case there (Load case) and fit "
                             "it, or choose the case and fit folders here")
        if not fit or not os.path.isfile(os.path.join(fit, "fitting_mesh.vtu")):
            raise ValueError(f"Breast Optimization's output folder {fit!r} holds no finished fit: run the fit to its "
                             "end first")
        record = os.path.join(fit, "case.json")
        if os.path.isfile(record):
            with open(record, encoding="utf-8") as file:
                case = json.load(file).get("case_dir") or case
        if not case:
            raise ValueError("Breast Optimization has no case folder: load a compressed case there (Load case) and fit "
                             "it, or choose the case and fit folders here")
        parameterNode["caseDirectory"], parameterNode["fitDirectory"] = case, fit

    def openSession(self, parameterNode, progress=None):
        """The diagnosis session of the chosen case, fit and output folder (kept while they stay
        the same; an output folder holding this case's and fit's earlier rounds goes on after
        them). Loads the measured compressed volume into the scene."""
        from BreastBiomechLib.discrepancy import DiagnosisSession, DiagnosisSettings, NoiseModel
        from BreastBiomechLib.discrepancy.registration import RegistrationSettings
        from BreastBiomechLib.discrepancy.session import FLOOR_FILE
        from BreastBiomechLib.mrml import image_to_volume_node

        p = parameterNode
        case = chosen_folder(p["caseDirectory"], "the compressed case folder (it holds mr.nrrd and compressed/)")
        fit = chosen_folder(p["fitDirectory"], "the fit folder (breastbiomech optimise --out, or Breast "
                                                   "Optimization's output folder)")
        out = chosen_folder(p["outputDirectory"], "an output folder for the rounds and the report")
        effects = [e.strip() for e in p["effects"].replace(",", " ").split() if e.strip()] or None
        key = (case, fit, out, tuple(effects or ()), p["landmarkSdMm"], p["modelSdMm"], p["measuredFloor"], p["alpha"],
               p["residualField"])
        if self.session is not None and self._key == key:
            return self.session
        # a session started there: its rounds, or only the floor it measured before a Cancel
        earlier = any(os.path.isfile(os.path.join(out, name)) for name in ("diagnosis.json", FLOOR_FILE))
        if not earlier and os.path.isdir(out) and os.listdir(out):
            raise ValueError(f"the output folder {out} is not empty and holds no diagnosis: choose a new or empty folder")
        session = DiagnosisSession(case, fit, out, effects,
                                   NoiseModel(landmark_sd_mm=p["landmarkSdMm"], model_sd_mm=p["modelSdMm"],
                                              floor="measured" if p["measuredFloor"] else "fixed"),
                                   # refined, and its interval made, when an effect is added (accept)
                                   DiagnosisSettings(alpha=p["alpha"], refine_iterations=0, profile=False),
                                   self.resolveDevice(p["device"]), resume=earlier,
                                   registration=RegistrationSettings() if p["residualField"] else None,
                                   progress=progress)
        self.session, self._key, self._surface = session, key, None
        p.set_reference("measuredVolume", image_to_volume_node(session.fitted.measured_image, self.scene,
                                                               "Measured compressed MR",
                                                               node=p.reference("measuredVolume")))
        return session

    @staticmethod
    def resolveDevice(choice: str) -> str:
        return resolve_device(choice)

    # -- the steps -------------------------------------------------------------------------------

    def diagnose(self, parameterNode, progress=None):
        """Diagnose the next round (an open one again). ``progress(message)`` answering False
        cancels before anything is written or added to the scene. Returns the candidates table
        node (ranked as the library ranks them)."""
        p = parameterNode
        session = self.openSession(p, progress)
        last = session.last
        from BreastBiomechLib.discrepancy.session import is_open

        if last is not None and not is_open(last) and len(session.rounds) >= p["maxRounds"]:
            raise ValueError(f"{len(session.rounds)} rounds made, the most allowed ({p['maxRounds']}): raise Rounds "
                             "to go on")
        return self._showDiagnosed(p, session.diagnose(progress))

    def _showDiagnosed(self, parameterNode, record):
        """A round just diagnosed into the scene: its candidates table, overlays and plots (the
        nodes of an open round diagnosed again replaced). Returns the table node."""
        p, number = parameterNode, record["round"]
        self._removeRound(number)  # an open round diagnosed again: its old nodes go
        folder = self._roundFolder(number)
        table = self._candidatesTable(p, record, folder)
        self._evidence(p, record, "before", folder)
        p["shownRound"], p["candidate"] = number, record["diagnosis"]["effect"] or ""
        self._plots(p, record, folder)
        logging.info("BreastDiscrepancy: round %d: %s", number, record["diagnosis"]["sentence"])
        return table

    def accept(self, parameterNode, name=None, progress=None) -> dict:
        """*Refit with effect*: add candidate ``name`` (default the round's verdict, else the
        selected candidate) to the model and refit it, warm-started, refined by
        "refineIterations" Gauss-Newton iterations, with its parameters' profile intervals; the
        overlays and plots after the refit join the round's folder. Cancelling leaves the round as it was. Returns the round's record."""
        p = parameterNode
        session = self._session(p)
        return self._showAccepted(p, session.add(self._toAdd(p, session, name), p["refineIterations"], progress,
                                                 profile=True))

    @staticmethod
    def _toAdd(parameterNode, session, name=None) -> str:
        """The candidate *Refit with effect* adds: ``name``, else the round's verdict, else the
        selected candidate."""
        record = session.last
        name = name or record["diagnosis"]["effect"] or parameterNode["candidate"]
        if not name:
            raise ValueError(f"round {record['round']} names no effect ({record['diagnosis']['verdict']}): select a "
                             "candidate in the table to add it anyway, or diagnose again")
        return name

    def _showAccepted(self, parameterNode, record) -> dict:
        """A round whose effect was just added into the scene: the overlays and plots after the
        refit join the round's folder. Returns the record."""
        p = parameterNode
        folder = self._roundFolder(record["round"])
        self._evidence(p, record, "after", folder)
        self._candidatesTable(p, record, folder)
        self._plots(p, record, folder)
        p["candidate"] = record["added"]
        logging.info("BreastDiscrepancy: round %d: added %s", record["round"], record["added"])
        return record

    # -- the long steps out of Slicer's process ---------------------------------------------------

    def commandArguments(self, parameterNode) -> list[str]:
        """`breastbiomech diagnose` with the panel's case, fit, output folder and settings (what
        :meth:`openSession` passes to the session in this process)."""
        p = parameterNode
        case = chosen_folder(p["caseDirectory"], "the compressed case folder (it holds mr.nrrd and compressed/)")
        fit = chosen_folder(p["fitDirectory"], "the fit folder (breastbiomech optimise --out, or Breast "
                                                   "Optimization's output folder)")
        out = chosen_folder(p["outputDirectory"], "an output folder for the rounds and the report")
        effects = [e.strip() for e in p["effects"].replace(",", " ").split() if e.strip()]
        from BreastBiomechLib.discrepancy.session import FLOOR_FILE

        earlier = any(os.path.isfile(os.path.join(out, name)) for name in ("diagnosis.json", FLOOR_FILE))
        if not earlier and os.path.isdir(out) and os.listdir(out):
            raise ValueError(f"the output folder {out} is not empty and holds no diagnosis: choose a new or empty folder")
        if p["device"] not in ("auto", "cuda", "cpu"):
            raise ValueError(f"device must be auto, cuda or cpu, not {p['device']!r}")
        arguments = ["diagnose", case, "--fit", fit, "--out", out, "--rounds", str(p["maxRounds"]),
                     "--landmark-sd-mm", repr(float(p["landmarkSdMm"])), "--model-sd-mm", repr(float(p["modelSdMm"])),
                     "--floor", "measured" if p["measuredFloor"] else "fixed", "--alpha", repr(float(p["alpha"])),
                     "--refine-iterations", str(p["refineIterations"])]
        arguments += ["--effects", *effects] if effects else []
        arguments += [] if p["residualField"] else ["--no-residual-field"]
        arguments += [] if p["device"] == "auto" else ["--device", p["device"]]
        return arguments + (["--resume"] if earlier else [])

    def startDiagnosis(self, parameterNode):
        """*Diagnose* out of Slicer's process: `breastbiomech diagnose --one-round` diagnoses the
        next round (an open one again) and stops before adding anything, its diagnosis kept in the
        output folder. Returns the running :class:`~BreastBiomechCommon.worker.CommandWorker`;
        once it has ended :meth:`finishDiagnosis` shows the round. Cancel (the worker's) keeps
        what was finished (the measured floor, earlier rounds)."""
        from BreastBiomechCommon.worker import CommandWorker

        arguments = self.commandArguments(parameterNode) + ["--one-round"]
        self.session, self._key = None, None  # the folder is about to change under it
        return CommandWorker(arguments, folder=parameterNode["outputDirectory"]).start()

    def finishDiagnosis(self, parameterNode, worker):
        """The round an ended :meth:`startDiagnosis` diagnosed into the scene (the session opened
        again from the output folder, the round's kept diagnosis with it). Raises RuntimeError
        with the worker's reason where it failed or was cancelled. Returns the candidates table."""
        self._ended(worker, "the diagnosis")
        session = self.openSession(parameterNode)
        if session.last is None:
            raise RuntimeError("the diagnosis wrote no round")
        return self._showDiagnosed(parameterNode, session.last)

    def startAccept(self, parameterNode, name=None):
        """*Refit with effect* out of Slicer's process: `breastbiomech diagnose --resume --add NAME`
        adds the candidate (``name``, else the verdict's, else the selected one) to the open
        round's model and refits it from the round's kept diagnosis. Returns the running worker;
        once it has ended :meth:`finishAccept` shows the refit."""
        from BreastBiomechCommon.worker import CommandWorker

        p = parameterNode
        session = self._session(p)
        name = self._toAdd(p, session, name)
        if session.last.get("added"):
            raise ValueError(f"round {session.last['round']} already added {session.last['added']}: diagnose the "
                             "next round")
        arguments = self.commandArguments(p)
        if "--resume" not in arguments:
            arguments.append("--resume")
        self.session, self._key = None, None
        return CommandWorker(arguments + ["--add", name], folder=p["outputDirectory"]).start()

    def finishAccept(self, parameterNode, worker) -> dict:
        """The refit of an ended :meth:`startAccept` into the scene. Raises RuntimeError with the
        worker's reason where it failed or was cancelled (the round then stays as it was).
        Returns the round's record."""
        self._ended(worker, "the refit")
        record = self.openSession(parameterNode).last
        if not record.get("added"):
            raise RuntimeError("the refit added nothing")
        return self._showAccepted(parameterNode, record)

    def designNext(self, parameterNode, progress=None):
        """*Design next measurement* in this process: after the last round (decided), the
        acquisitions of the library (``designAcquisitions``: kinds or names, blank: all) simulated
        from the current model, and each one's separation of the candidates the round could not
        tell apart from their closest rivals and the fitted parameters
        (:meth:`~BreastBiomechLib.discrepancy.session.DiagnosisSession.design`). Returns the
        design's table node."""
        p = parameterNode
        session = self.openSession(p, progress)
        return self._showDesign(p, session.design(self._acquisitions(p), progress))

    @staticmethod
    def _acquisitions(parameterNode) -> list[str]:
        return [a.strip() for a in parameterNode["designAcquisitions"].replace(",", " ").split() if a.strip()]

    def startDesign(self, parameterNode):
        """*Design next measurement* out of Slicer's process: `breastbiomech diagnose --resume
        --design [ACQUISITIONS]` on the output folder's decided rounds. Returns the running worker;
        once it has ended :meth:`finishDesign` shows the design."""
        from BreastBiomechCommon.worker import CommandWorker
        from BreastBiomechLib.discrepancy.session import is_open

        p = parameterNode
        session = self._session(p)
        if is_open(session.last):
            raise ValueError(f"round {session.last['round']} waits for a decision: refit with its effect or reject it "
                             "first")
        arguments = self.commandArguments(p)
        if "--resume" not in arguments:
            arguments.append("--resume")
        arguments[arguments.index("--rounds") + 1] = str(len(session.rounds))  # after the rounds made: none further
        self.session, self._key = None, None
        return CommandWorker(arguments + ["--design", *self._acquisitions(p)], folder=p["outputDirectory"]).start()

    def finishDesign(self, parameterNode, worker):
        """The design of an ended :meth:`startDesign` into the scene. Raises RuntimeError with the
        worker's reason where it failed or was cancelled. Returns the design's table node."""
        from BreastBiomechLib.discrepancy.design_record import read_design

        self._ended(worker, "the design")
        session = self.openSession(parameterNode)
        record = read_design(session.out, session.last["round"])
        if record is None:
            raise RuntimeError("the design wrote nothing for the last round")
        return self._showDesign(parameterNode, record)

    def _showDesign(self, parameterNode, record):
        """A design (design.json's ``record``) as the table "Round N: next measurement" in its
        round's folder: per candidate designed for, its closest rival, the separation it needs and
        has now, and with each acquisition (sigma; NaN where its secant did not solve there); one
        row saying so where every candidate was told apart. The parameter node's shown round
        becomes that round."""
        from BreastBiomechLib.mrml import columns_to_table_node

        number = record["round"]
        names = [a["name"] for a in record["acquisitions"]]
        rows = record["effects"]
        nothing = "outside the chosen effects: " + ", ".join(record["undecided"]) if record.get("undecided") \
            else "every tested candidate told apart"
        columns = {"effect": np.array([r["title"] for r in rows] or [nothing], dtype=object),
                   "rival": np.array([r.get("rival_title") or "-" for r in rows] or ["-"], dtype=object),
                   "needed (sigma)": np.array([r["detectable_sigma"] for r in rows] or [float("nan")], float),
                   "now (sigma)": np.array([r["now_sigma"] for r in rows] or [float("nan")], float)}
        for name in names:
            seen = [{a["name"]: a["separation_sigma"] for a in r["acquisitions"]}.get(name, float("nan")) for r in rows]
            columns[f"{name} (sigma)"] = np.array(seen or [float("nan")], float)
        node = columns_to_table_node(columns, self.scene, f"Round {number}: next measurement",
                                     node=self._kindNode(number, "design"))
        parameterNode.set_reference("designTable", self._put(self._roundFolder(number), number, "design", node))
        parameterNode["shownRound"] = number
        return node

    def designText(self, parameterNode) -> str:
        """The sentences of the design made after the shown round ("" where none was)."""
        from BreastBiomechLib.discrepancy.design_record import design_sentences, read_design

        folder = self._folder(parameterNode) if parameterNode is not None else None
        record = read_design(folder, parameterNode["shownRound"]) if folder else None
        return "\n".join(f"Next measurement: {s}" for s in design_sentences(record)) if record else ""

    @staticmethod
    def _ended(worker, what: str) -> None:
        if worker.running:
            raise RuntimeError(f"{what} is still running: wait for it or cancel it")
        if worker.cancelled:
            raise RuntimeError(f"{what} was cancelled; what it had finished is kept in the output folder")
        if not worker.succeeded:
            raise RuntimeError(worker.error or f"{what} ended without a result")

    def reject(self, parameterNode, name=None) -> str:
        """Turn candidate ``name`` (default the selected one, else the verdict's) down: the next
        round does not test it. Returns its name."""
        p = parameterNode
        session = self._session(p)
        name = name or p["candidate"] or session.last["diagnosis"]["effect"]
        if not name:
            raise ValueError("select the candidate to reject in the table")
        record = session.reject(name)
        self._candidatesTable(p, record, self._roundFolder(record["round"]))
        return name

    def _session(self, parameterNode=None):
        """The open session; where there is none (a module Reload, a saved scene loaded again, a
        scene closed) but the parameter node's output folder holds a diagnosis, it is opened
        from there, so that the rounds in the scene are reachable again."""
        if self.session is None and parameterNode is not None and parameterNode["outputDirectory"] and \
                os.path.isfile(os.path.join(parameterNode["outputDirectory"], "diagnosis.json")):
            self.openSession(parameterNode)
        if self.session is None or self.session.last is None:
            raise ValueError("diagnose first")
        return self.session

    def _folder(self, parameterNode=None) -> str | None:
        """The output folder whose round nodes the panel shows: the open session's, else the
        parameter node's (None: neither)."""
        if self.session is not None:
            return str(self.session.out)
        if parameterNode is not None and parameterNode["outputDirectory"]:
            return str(Path(parameterNode["outputDirectory"]))
        return None

    # -- what the scene shows --------------------------------------------------------------------

    def roundNumbers(self, parameterNode=None) -> list[int]:
        """The rounds whose nodes are in the scene, in order."""
        numbers = set()
        for node in self._roundNodes(parameterNode):
            numbers.add(int(node.GetAttribute(ROUND_ATTRIBUTE)))
        return sorted(numbers)

    def verdictText(self, parameterNode) -> str:
        """The shown round's verdict sentence, with what was added or rejected ("" with no session
        or no parameter node)."""
        if self.session is None or parameterNode is None:
            return ""
        record = next((r for r in self.session.rounds if r["round"] == parameterNode["shownRound"]), None)
        if record is None:
            return ""
        text = f"Round {record['round']}: {record['diagnosis']['sentence']}"
        if record.get("added"):
            after = record["after"].get("landmark_error_mm")
            before = record["before"].get("landmark_error_mm")
            text += f"\nAdded {record['added']}" + (f": landmark error {before['mean']:.2f} -> {after['mean']:.2f} mm"
                                                     if before and after else "")
        if record.get("rejected"):
            text += f"\nRejected: {', '.join(record['rejected'])}"
        design = self.designText(parameterNode)
        return f"{text}\n{design}" if design else text

    def candidateAtRow(self, parameterNode, row: int) -> str:
        """The candidate's name in ``row`` of the shown round's candidates table."""
        table = parameterNode.reference("candidatesTable")
        if table is None or not 0 <= row < table.GetNumberOfRows():
            raise ValueError(f"the candidates table has no row {row}")
        name = table.GetCellText(row, 1)
        parameterNode["candidate"] = name
        return name

    def showCandidate(self, parameterNode, name: str):
        """The residual candidate ``name`` predicts (its linearised estimate's change of the model,
        magnitude in mm on the measured grid, the residual's colour scale), beside the measured
        residual (application: side-by-side slice views). Returns the volume node."""
        from BreastBiomechLib.discrepancy.evidence import candidate_pattern
        from BreastBiomechLib.mrml import image_to_volume_node
        from BreastBiomechLib.mrml.overlays import MAGNITUDE_COLORS, put_in_folder, show_as_overlay

        p = parameterNode
        session = self._session(p)
        if p.reference("measuredVolume") is None:
            raise ValueError("the measured compressed volume is no longer in the scene (was the scene closed?): "
                             "diagnose again to load it")
        diagnosis, number = session.diagnosis, session.last["round"]
        if diagnosis is None:
            raise ValueError(f"round {number} was diagnosed in an earlier session whose diagnosis is not kept (an "
                             "older library, or its kept file removed): diagnose again to see what a candidate predicts")
        candidate = next((c for c in diagnosis.candidates if c.name == name), None)
        if candidate is None or candidate.skipped or name not in diagnosis.sensitivities.fields:
            raise ValueError(f"{name!r} was not tested in round {number}: no predicted residual to show")
        image = candidate_pattern(session.fitted, diagnosis.sensitivities.displacement,
                                  diagnosis.sensitivities.fields[name], candidate.estimate)
        node = self._kindNode(number, f"candidate-{name}") or image_to_volume_node(
            image, self.scene, f"Round {number}: residual {candidate.title} predicts")
        image_to_volume_node(image, self.scene, node=node)
        self._tag(node, number, f"candidate-{name}")
        show_as_overlay(node, MAGNITUDE_COLORS, 0.0, self._limit(number), "predicted |r| (mm)", SHOWN_FROM_MM)
        put_in_folder(self.scene, [node], self._roundFolder(number))
        p.set_reference("candidateVolume", node)
        p["candidate"] = name
        if IN_SLICER_APPLICATION:
            from BreastBiomechLib.mrml.views import compare_side_by_side

            layout = slicer.app.layoutManager()
            layout.setLayout(slicer.vtkMRMLLayoutNode.SlicerLayoutSideBySideView)
            residual = p.reference("residualVolume")
            compare_side_by_side([(layout.sliceWidget(view).mrmlSliceNode(),
                                   layout.sliceWidget(view).mrmlSliceCompositeNode()) for view in ("Red", "Yellow")],
                                 p.reference("measuredVolume").GetID(),
                                 [residual.GetID() if residual is not None else None, node.GetID()])
        return node

    def showRound(self, parameterNode, number: int) -> None:
        """Point the panel's nodes at round ``number``'s (after its refit where there was one):
        the residual overlay, field, landmark lines, skin model, regions, candidates table, plots
        and the next measurement's table where one was designed after it; in the application the
        overlay lies over the measured volume."""
        p = parameterNode
        if number not in self.roundNumbers(p):
            raise ValueError(f"round {number} is not in the scene (rounds: {self.roundNumbers(p)})")
        self._session(p)  # taken up from the output folder after a Reload or a saved scene
        when = "after" if self._kindNode(number, "residual-after") or self._kindNode(number, "lines-after") else "before"
        for role, kind in (("residualVolume", f"residual-{when}"), ("residualTransform", f"field-{when}"),
                           ("landmarkLines", f"lines-{when}"), ("skinModel", f"skin-{when}"), ("regions", "regions"),
                           ("candidatesTable", "candidates"), ("landmarkErrorsTable", "landmark-errors"),
                           ("landmarkErrorsChart", "landmark-errors-chart"), ("measuresTable", "measures"),
                           ("measuresChart", "measures-chart"), ("histogramTable", "histogram"),
                           ("histogramChart", "histogram-chart"), ("designTable", "design")):
            p.set_reference(role, self._kindNode(number, kind))
        p["shownRound"] = number
        for other in self._roundNodes():
            if other.IsA("vtkMRMLDisplayableNode") and other.GetDisplayNode() is not None:
                mine = int(other.GetAttribute(ROUND_ATTRIBUTE)) == number and other.GetAttribute(
                    KIND_ATTRIBUTE).endswith(when)
                if other.IsA("vtkMRMLModelNode"):
                    other.GetDisplayNode().SetVisibility(mine)
        self.setGlyphsVisible(p, p["fieldGlyphs"])
        self.setRegionsVisible(p, p["showRegions"])
        if IN_SLICER_APPLICATION and p.reference("measuredVolume") is not None:
            slicer.util.setSliceViewerLayers(background=p.reference("measuredVolume"),
                                             foreground=p.reference("residualVolume"), foregroundOpacity=0.7)
            if p.reference("landmarkErrorsChart") is not None:
                slicer.modules.plots.logic().ShowChartInLayout(p.reference("landmarkErrorsChart"))

    def setGlyphsVisible(self, parameterNode, visible: bool) -> None:
        """Show or hide the shown round's residual field as glyphs in the slice views."""
        parameterNode["fieldGlyphs"] = bool(visible)
        for node in self._roundNodes(parameterNode):
            if node.IsA("vtkMRMLTransformNode") and node.GetDisplayNode() is not None:
                node.GetDisplayNode().SetVisibility(bool(visible) and node is parameterNode.reference("residualTransform"))

    def setRegionsVisible(self, parameterNode, visible: bool) -> None:
        """Show or hide the shown round's regions (segments: contact bands, chest-wall band,
        sub-surface band, deeper tissue)."""
        parameterNode["showRegions"] = bool(visible)
        for node in self._roundNodes(parameterNode):
            if node.IsA("vtkMRMLSegmentationNode") and node.GetDisplayNode() is not None:
                node.GetDisplayNode().SetVisibility(bool(visible) and node is parameterNode.reference("regions"))

    def saveReport(self, parameterNode, capture=None):
        """Write the diagnosis report (Markdown: each round's verdict, ranked candidates, residual by
        region, before/after, residual maps) into the output folder, with a picture of the slice
        views made by ``capture(path)`` where given (the application's screenshot). Returns its path."""
        from BreastBiomechLib.discrepancy.report import write_report

        session = self._session(parameterNode)
        pictures = []
        if capture is not None:
            picture = Path(session.out) / f"round-{parameterNode['shownRound']}-slice-views.png"
            capture(picture)
            pictures.append((f"Slice views of round {parameterNode['shownRound']} in Slicer", picture.name))
        return write_report(session.run(), Path(session.out) / "report.md", pictures)

    # -- nodes of a round ------------------------------------------------------------------------

    def _roundNodes(self, parameterNode=None) -> list:
        """The round nodes of the output folder (:meth:`_folder`): found by their attributes, so
        that they are found again in a saved scene loaded again or after a module Reload."""
        folder = self._folder(parameterNode)
        if folder is None:
            return []
        nodes = []
        for i in range(self.scene.GetNumberOfNodes()):
            node = self.scene.GetNthNode(i)
            if node.GetAttribute(ROUND_ATTRIBUTE) is not None and node.GetAttribute(FOLDER_ATTRIBUTE) == folder:
                nodes.append(node)
        return nodes

    def _kindNode(self, number: int, kind: str):
        return next((n for n in self._roundNodes() if n.GetAttribute(ROUND_ATTRIBUTE) == str(number)
                     and n.GetAttribute(KIND_ATTRIBUTE) == kind), None)

    def _tag(self, node, number: int, kind: str):
        node.SetAttribute(ROUND_ATTRIBUTE, str(number))
        node.SetAttribute(KIND_ATTRIBUTE, kind)
        node.SetAttribute(FOLDER_ATTRIBUTE, str(self.session.out))
        return node

    def _roundFolder(self, number: int) -> int:
        """The subject-hierarchy folder "Round N" under "Discrepancy <output folder's name>"."""
        from BreastBiomechLib.mrml.overlays import folder

        return folder(self.scene, f"Round {number}", folder(self.scene, f"Discrepancy {self.session.out.name}"))

    def _removeRound(self, number: int) -> None:
        """Remove round ``number``'s nodes with what they own (display and colour-legend nodes,
        plot series), so that a round diagnosed again leaves nothing behind."""
        from BreastBiomechLib.mrml.overlays import remove_with_what_it_owns

        for node in self._roundNodes():
            if node.GetAttribute(ROUND_ATTRIBUTE) == str(number):
                remove_with_what_it_owns(self.scene, node)

    def _limit(self, number: int) -> float:
        """The colour scale's top (mm) of round ``number``: the 99th percentile of its residual
        magnitude before the refit (at least 0.5 mm), shared by every overlay of the round."""
        field = self.session.fields.get((number, "before"))
        if field is None or not field.mask.any():
            return 2.0
        return max(float(np.percentile(field.magnitude[field.mask], 99)), 0.5)

    def _put(self, folder_item, number, kind, node):
        from BreastBiomechLib.mrml.overlays import put_in_folder

        self._tag(node, number, kind)
        put_in_folder(self.scene, [node], folder_item)
        return node

    def _candidatesTable(self, parameterNode, record, folder_item):
        """The round's candidates as a table: rank, effect name and title, score statistic (dof),
        corrected p, share of the residual it could explain, localisation, share of its signature
        the fitted parameters reproduce, the smallest size of its parameters its test would see,
        refit dBIC and share removed, where it acts, and its part in the verdict."""
        from BreastBiomechLib.discrepancy.diagnosis import closest_rivals
        from BreastBiomechLib.mrml import columns_to_table_node

        d = record["diagnosis"]
        rows = [c for c in d["candidates"] if not c["skipped"]] + [c for c in d["candidates"] if c["skipped"]]

        def role(c):
            if c["skipped"]:
                return f"skipped: {c['skipped']}"
            if c["name"] in record.get("rejected", []):
                return "rejected"
            if c["name"] == record.get("added"):
                return "added"
            if c["name"] == d["effect"]:
                return "missing effect"
            if c["name"] in d["alternatives"]:
                return "ambiguous" if d["verdict"] == "ambiguous" else "unexplained: the nearest candidate"
            if c["p_adjusted"] < 0.01 or (c.get("refit") or {}).get("delta_bic") is not None:
                return "significant, not confirmed"
            return "not significant"

        def refit(c, key):
            value = (c.get("refit") or {}).get(key)
            return float("nan") if value is None else float(value)

        rivals = closest_rivals(d["candidates"], d.get("correlations") or {})

        def rival(c):  # the tested candidate it is least told apart from, and their correlation
            found = rivals.get(c["name"])
            return "-" if found is None else f"{found[0]} {found[1]:.2f}"

        def detectable(c):  # per parameter, its units ("-": not computed; "none": the fit takes it up whole)
            sizes = c.get("detectable") or []
            return ", ".join("none" if v is None else f"{v:.2g}" for v in sizes) or "-"

        columns = {"rank": np.array([str(i + 1) if not c["skipped"] else "-" for i, c in enumerate(rows)], dtype=object),
                   "effect": np.array([c["name"] for c in rows], dtype=object),
                   "title": np.array([c["title"] for c in rows], dtype=object),
                   "statistic": np.array([c["statistic"] for c in rows], float),
                   "dof": np.array([c["dof"] for c in rows], float),
                   "linearised dBIC": np.array([c.get("linear_delta_bic", float("nan")) for c in rows], float),
                   "p (corrected)": np.array([c["p_adjusted"] for c in rows], float),
                   "could explain": np.array([c["explained_fraction"] for c in rows], float),
                   "localisation": np.array([c["localisation"] for c in rows], float),
                   "absorbed by fit": np.array([c.get("absorbed", float("nan")) for c in rows], float),
                   "closest rival": np.array([rival(c) for c in rows], dtype=object),
                   "smallest size seen": np.array([detectable(c) for c in rows], dtype=object),
                   "dBIC": np.array([refit(c, "delta_bic") for c in rows], float),
                   "removed": np.array([refit(c, "removed") for c in rows], float),
                   "change (mm)": np.array([refit(c, "effect_mm") for c in rows], float),
                   "acts in": np.array([c.get("acts_in", "") for c in rows], dtype=object),
                   "verdict": np.array([role(c) for c in rows], dtype=object)}
        number = record["round"]
        node = columns_to_table_node(columns, self.scene, f"Round {number}: candidates",
                                     node=self._kindNode(number, "candidates"))
        parameterNode.set_reference("candidatesTable", self._put(folder_item, number, "candidates", node))
        return node

    def _evidence(self, parameterNode, record, when, folder_item) -> None:
        """The round's overlays ``when`` ("before" or "after" its refit): residual magnitude volume
        with a colour legend, residual field as a grid transform (glyphs), landmark residual lines,
        skin signed-distance model; before: the regions."""
        import SimpleITK as sitk

        from BreastBiomechLib.discrepancy.evidence import landmark_residuals, region_labels, skin_surface
        from BreastBiomechLib.mrml import displacement_field_to_grid_transform_node, image_to_volume_node
        from BreastBiomechLib.mrml.overlays import (
            MAGNITUDE_COLORS,
            segments_to_model_node,
            show_as_overlay,
            surface_to_model_node,
        )
        from BreastBiomechLib.mrml.segmentations import named_labels_to_segmentation_node
        from BreastBiomechLib.similarity.surface import SurfaceDistance

        p = parameterNode
        session, number = self.session, record["round"]
        diagnosis = session.diagnosis
        displacement = diagnosis.sensitivities.displacement if when == "before" else diagnosis.refitted.displacement
        label = "before" if when == "before" else f"after adding {record['added']}"
        field = session.fields.get((number, when))
        if field is not None:
            volume = image_to_volume_node(field.magnitude_image(), self.scene,
                                          f"Round {number}: residual |r| {label}",
                                          node=self._kindNode(number, f"residual-{when}"))
            show_as_overlay(volume, MAGNITUDE_COLORS, 0.0, self._limit(number), "residual |r| (mm)", SHOWN_FROM_MM)
            p.set_reference("residualVolume", self._put(folder_item, number, f"residual-{when}", volume))
            transform = displacement_field_to_grid_transform_node(
                sitk.Cast(field.image(), sitk.sitkVectorFloat64), self.scene, f"Round {number}: residual field {label}",
                node=self._kindNode(number, f"field-{when}"))
            if transform.GetDisplayNode() is None:
                transform.CreateDefaultDisplayNodes()
            display = transform.GetDisplayNode()
            display.SetVisualizationMode(display.VIS_MODE_GLYPH)
            display.SetVisibility2D(True)
            display.SetVisibility(False)
            p.set_reference("residualTransform", self._put(folder_item, number, f"field-{when}", transform))
        residuals = landmark_residuals(session.fitted, displacement)
        if residuals is not None:
            lines = segments_to_model_node(residuals.predicted, residuals.measured, residuals.error_mm, "residual_mm",
                                           self.scene, f"Round {number}: landmark residuals {label}",
                                           node=self._kindNode(number, f"lines-{when}"))
            p.set_reference("landmarkLines", self._put(folder_item, number, f"lines-{when}", lines))
        if self._surface is None:
            self._surface = SurfaceDistance(session.fitted.measured_image)
        points, triangles, distance = skin_surface(session.fitted, displacement, self._surface)
        skin = surface_to_model_node(points, triangles, distance, "signed_distance_mm", self.scene,
                                     f"Round {number}: skin distance {label}", node=self._kindNode(number, f"skin-{when}"))
        p.set_reference("skinModel", self._put(folder_item, number, f"skin-{when}", skin))
        if when == "before":
            from BreastBiomechLib.discrepancy.regions import regions_of

            node_regions = regions_of(session.fitted, session.fitted.mesh.nodes, session.fitted.first(displacement))
            image, segments = region_labels(session.fitted, displacement, node_regions)
            regions = named_labels_to_segmentation_node(image, segments, self.scene, f"Round {number}: regions",
                                                        node=self._kindNode(number, "regions"))
            regions.GetDisplayNode().SetVisibility(bool(p["showRegions"]))
            p.set_reference("regions", self._put(folder_item, number, "regions", regions))

    def _plots(self, parameterNode, record, folder_item) -> None:
        """The round's plots: landmark error per landmark, NMI and RMS feature residual, and the
        residual magnitude's histogram, before and (once refitted) after."""
        from BreastBiomechLib.discrepancy.evidence import magnitude_histogram
        from BreastBiomechLib.mrml import columns_to_table_node, plot_chart_node

        p, number = parameterNode, record["round"]
        stages = [("before", record["before"])] + ([("after", record["after"])] if record.get("after") else [])
        errors = record["before"].get("landmark_error_mm")
        if errors:
            labels = list(errors["per_landmark"])
            columns = {"landmark": np.array(labels, dtype=object), "index": np.arange(1, len(labels) + 1, dtype=float)}
            for stage, measures in stages:
                columns[f"error {stage} (mm)"] = np.array([measures["landmark_error_mm"]["per_landmark"][k]
                                                           for k in labels], float)
            table = columns_to_table_node(columns, self.scene, f"Round {number}: landmark errors",
                                          node=self._kindNode(number, "landmark-errors"))
            p.set_reference("landmarkErrorsTable", self._put(folder_item, number, "landmark-errors", table))
            chart = plot_chart_node(table, "index", [f"error {s} (mm)" for s, _ in stages], self.scene,
                                    f"Round {number}: landmark error", "error (mm)",
                                    node=self._kindNode(number, "landmark-errors-chart"), bars=True)
            p.set_reference("landmarkErrorsChart", self._put(folder_item, number, "landmark-errors-chart", chart))
        columns = {"stage": np.array([s for s, _ in stages], dtype=object),
                   "index": np.arange(1, len(stages) + 1, dtype=float),
                   "NMI": np.array([m["nmi"] for _, m in stages], float),
                   "RMS feature residual (mm)": np.array([m["residual_rms_mm"] for _, m in stages], float),
                   "mean landmark error (mm)": np.array([m["landmark_error_mm"]["mean"] if m.get("landmark_error_mm")
                                                         else np.nan for _, m in stages], float)}
        for state in record["before"].get("states") or {}:  # a joint fit's further measured states
            columns[f"NMI {state}"] = np.array([m["states"][state]["nmi"] for _, m in stages], float)
            columns[f"mean landmark error {state} (mm)"] = np.array(
                [m["states"][state]["landmark_error_mm"]["mean"] if m["states"][state].get("landmark_error_mm")
                 else np.nan for _, m in stages], float)
        table = columns_to_table_node(columns, self.scene, f"Round {number}: measures",
                                      node=self._kindNode(number, "measures"))
        p.set_reference("measuresTable", self._put(folder_item, number, "measures", table))
        chart = plot_chart_node(table, "index", ["NMI"], self.scene, f"Round {number}: NMI (1 before, 2 after)",
                                "NMI", node=self._kindNode(number, "measures-chart"), bars=True)
        p.set_reference("measuresChart", self._put(folder_item, number, "measures-chart", chart))
        fields = {f"share {when}": self.session.fields[(number, when)] for when, _ in stages
                  if (number, when) in self.session.fields}
        if fields:
            table = columns_to_table_node(magnitude_histogram(fields), self.scene, f"Round {number}: residual histogram",
                                          node=self._kindNode(number, "histogram"))
            p.set_reference("histogramTable", self._put(folder_item, number, "histogram", table))
            chart = plot_chart_node(table, "|r| (mm)", list(fields), self.scene, f"Round {number}: residual |r|",
                                    "share of the breast's voxels", node=self._kindNode(number, "histogram-chart"))
            p.set_reference("histogramChart", self._put(folder_item, number, "histogram-chart", chart))


#
# Test (runs inside Slicer: Reload and Test; the thorough checks run headless in Testing/)
#


class BreastDiscrepancyTest(ModuleTestMixin, ScriptedLoadableModuleTest):
    REQUIRES = tuple(DEPENDENCIES + ["cma", "tetgen"])

    def test_diagnose_a_small_case_with_hidden_friction(self):
        """The headless test's case and settings (BreastBiomechLib.cli.examples.small_friction_case,
        Testing/modules/test_module_breastdiscrepancy.py): friction named among the whole library,
        on the CPU as there (about five minutes on two cores)."""
        import tempfile

        from BreastBiomechLib.cli.examples import small_friction_case

        self.delayDisplay("Making the small phantom with hidden plate friction and fitting it (12 solves, CPU)")
        folder = tempfile.mkdtemp()
        case, fit = small_friction_case(f"{folder}/example", device="cpu")
        logic = BreastDiscrepancyLogic()
        p = logic.getParameterNode()
        p["caseDirectory"], p["fitDirectory"], p["outputDirectory"] = str(case), str(fit), f"{folder}/diagnosis"
        p["effects"], p["refineIterations"], p["device"] = "", 1, "cpu"  # the whole library
        logic.diagnose(p)
        self.assertEqual(logic.session.last["diagnosis"]["effect"], "friction", logic.session.last["diagnosis"]["sentence"])
        logic.accept(p)
        logic.showRound(p, 1)
        self.delayDisplay("Test passed")
