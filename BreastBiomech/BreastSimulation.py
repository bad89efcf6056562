"""BreastSimulation: plate compression of a tetrahedral breast mesh with the GPU TLED solver.

Choose the mesh (a model node holding a tetrahedral unstructured grid, e.g. from BreastMesh or a
loaded .vtu), the per-tissue materials (a table), the compression plates (markups planes the user
can move) and the fixed node set; run on the GPU when there is one and on warp's CPU device
otherwise; get the deformed mesh, plate-force and energy curves and the solver's verdict.

Module, Widget, Logic and Test classes follow Slicer's scripted-module template. The Logic holds
no Qt and runs headless on the ``slicer-core`` wheel (see docs/developing.md).
"""

from __future__ import annotations

import logging

import numpy as np
import slicer
import vtk
from BreastBiomechCommon import (IN_SLICER_APPLICATION, ModuleBase, ModuleLogicBase, ModuleTestMixin,
                                 ModuleWidgetBase, ScriptedLoadableModuleTest, _, dependencies_ready,
                                 ensure_library_importable, resolve_device, unmet_requirements)

ensure_library_importable()

MODEL_DEPENDENCIES = ["numpy"]  # building the model: materials, plates, node sets
DEPENDENCIES = ["numpy", "scipy", "warp"]  # solving it


class BreastSimulation(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent)
        self.parent.title = _("Breast Simulation")
        self.parent.helpText = _("""
Nonlinear finite-element simulation of breast compression between rigid plates (TLED: explicit dynamics
on the GPU with NVIDIA warp, or dynamic relaxation to the static solution). Choose the tetrahedral mesh,
the tissue materials, the plates and the fixed chest-wall nodes, then Run. See docs/solver.md of the
<a href='https://github.com/BreastBiomech/BreastBiomech'>project</a>.
""")
        self.parent.acknowledgementText = _("""
Solver after NiftySim (Taylor et al. 2008) and Han et al. 2012, Phys. Med. Biol. 57:455; dynamic
relaxation after Joldes, Wittek and Miller.
""")


class BreastSimulationWidget(ModuleWidgetBase):
    def connectGUI(self):
        self.connectLogic(self.ui.inputMeshSelector.currentNodeChanged,
                          lambda parameterNode, node: self.logic.chooseDefaultNodeSets(parameterNode))
        self.ui.cancelButton.enabled = False
        # Nothing is installed or initialised when the panel opens (warp's start looks for CUDA
        # and loads its kernels' cache: seconds): the device is looked up at the first Run
        self.ui.deviceLabel.text = (_("warp is not installed yet: the first Run offers to install it")
                                    if unmet_requirements(["warp"]) else self.logic.deviceAtOpen())

    def showParameters(self, p):
        self.ui.materialsTableView.setMRMLTableNode(p.reference("materials"))
        self._fillNodeSetComboBoxes()  # the node sets of the chosen mesh, before the bindings choose among them
        self.ui.skinThicknessSpinBox.enabled = p["skinModulusKPa"] > 0
        self.ui.chestWallNormalStiffnessSpinBox.enabled = p["chestWallMode"] == "elastic"
        self.ui.chestWallTangentialStiffnessSpinBox.enabled = p["chestWallMode"] != "fixed"
        self.ui.fixedDirectionsWidget.enabled = p["chestWallMode"] == "fixed"
        self.ui.startUnloadedCheckBox.enabled = p["gravity"] != "none"
        physical = p["method"] == "physical"
        for widget in (self.ui.dampingSpinBox, self.ui.totalTimeSpinBox, self.ui.settleTimeSpinBox,
                       self.ui.stopWhenSettledCheckBox):
            widget.enabled = physical
        self.ui.toleranceSpinBox.enabled = not physical or p["stopWhenSettled"]
        plates = p.references("plates")
        self.ui.platesLabel.text = (", ".join(self._plateText(n) for n in plates)
                                    if plates else "none: press Place plates")
        self.ui.runButton.enabled = p.reference("inputMesh") is not None

    def _plateText(self, planeNode):
        try:
            return f"{planeNode.GetName()} ({self.logic.plateTravel(planeNode):.1f} mm)"
        except ValueError:
            return f"{planeNode.GetName()} (travel not a number)"

    def _fillNodeSetComboBoxes(self):
        names = self.logic.nodeSetNames(self._parameterNode.reference("inputMesh"))
        for comboBox, first in ((self.ui.fixedNodeSetComboBox, []), (self.ui.contactNodeSetComboBox, ["boundary"])):
            comboBox.clear()
            for name in first + names:
                comboBox.addItem(name)

    def onDefaultMaterialsButton(self):
        self.runAction(MODEL_DEPENDENCIES, _("Failed to make the materials table."), self.logic.createDefaultMaterials)

    def onPlacePlatesButton(self):
        self.runAction(MODEL_DEPENDENCIES, _("Failed to place the plates."), self.logic.createCompressionPlates)

    def onCancelButton(self):
        seconds = self.cancelWorker()
        if seconds:
            self.ui.statusLabel.text = _("Cancelled ({seconds:.1f} s to stop the solver); the earlier results are "
                                         "unchanged.").format(seconds=seconds)

    def onRunButton(self):
        if not dependencies_ready(DEPENDENCIES, _("Breast Simulation")):
            return
        with slicer.util.tryWithErrorDisplay(_("Simulation failed to start."), waitCursor=True):
            worker = self.logic.startRun(self._parameterNode)
            self._setRunning(True)
            self.ui.progressBar.value = 0
            self.ui.progressBar.setFormat(_("starting the solver"))
            self.startWorker(worker, self._runEnded, self.ui.progressBar)

    def _setRunning(self, running: bool) -> None:
        self.ui.runButton.enabled = not running
        self.ui.cancelButton.enabled = running

    def _runEnded(self, worker):
        """The solver's process has ended: its results into the scene (not after a Cancel)."""
        self._setRunning(False)
        if worker.cancelled:
            return
        with slicer.util.tryWithErrorDisplay(_("Simulation failed."), waitCursor=True):
            parameterNode = self.logic.getParameterNode()  # also when the module was left meanwhile
            result = self.logic.finishRun(parameterNode, worker)
            self.ui.progressBar.value = 100
            self.ui.deviceLabel.text = result["device"]
            self.ui.statusLabel.text = result["summary"]
            self.logic.showResults(parameterNode)


class BreastSimulationLogic(ModuleLogicBase):
    """Mesh, materials, plates and constraints from MRML nodes into a solver model; results back as
    nodes. No Qt: runs in Slicer and headless (slicer-core wheel).

    Node sets are point arrays of the mesh (nodes where the array is non-zero), e.g. ``chest_wall``.
    Directions LR, AP, SI are the patient axes (LPS x, y, z in the library, RAS in the scene).
    ``scene`` defaults to ``slicer.mrmlScene`` inside the application."""

    MODULE_NAME = "BreastSimulation"
    DEFAULTS = {"method": "relaxation", "formulation": "T4ANP", "device": "auto",
                "compressionAxis": "LR", "compressionPercent": 25.0, "movingPlates": "both",
                "fixedNodeSet": "", "fixLR": False, "fixAP": True, "fixSI": False, "anchor": True,
                "contactNodeSet": "boundary", "chestClearanceMm": -1.0, "damping": 50.0, "totalTime": 1.0, "settleTime": 0.25,
                "tolerance": 0.01, "stopWhenSettled": True,
                "plateFriction1": 0.0, "plateFriction2": 0.0, "chestWallMode": "fixed",
                "chestWallNormalStiffness": 0.0, "chestWallTangentialStiffness": 0.0,
                "gravity": "none", "startUnloaded": False, "skinModulusKPa": 0.0, "skinThicknessMm": 2.0}
    ROLES = ("inputMesh", "materials", "plates", "outputMesh", "history", "forceChart", "energyChart")
    PLATE_NAMES = {"LR": ("Right plate", "Left plate"), "AP": ("Anterior plate", "Posterior plate"),
                   "SI": ("Inferior plate", "Superior plate")}  # first: the lower coordinate in LPS
    KE_IE_LIMIT = 0.05  # the seed's quasi-static criterion
    GRAVITY = {"none": None, "anterior (prone)": (0.0, -9.81, 0.0), "posterior (supine)": (0.0, 9.81, 0.0),
               "inferior (upright)": (0.0, 0.0, -9.81)}  # LPS m/s^2: the direction gravity pulls the tissue

    # -- inputs ----------------------------------------------------------------------------------

    @staticmethod
    def inputMesh(parameterNode):
        """The chosen mesh as a TetMesh (LPS mm)."""
        from BreastBiomechLib.mrml import tetmesh_from_model_node

        node = parameterNode.reference("inputMesh")
        if node is None:
            raise ValueError("choose the input mesh: a model node holding a tetrahedral mesh")
        return tetmesh_from_model_node(node)

    @staticmethod
    def nodeSetNames(meshNode) -> list[str]:
        """Names of the mesh's point arrays that can serve as node sets (one component)."""
        if meshNode is None or meshNode.GetUnstructuredGrid() is None:
            return []
        data = meshNode.GetUnstructuredGrid().GetPointData()
        return sorted(data.GetArrayName(i) for i in range(data.GetNumberOfArrays())
                      if data.GetArray(i) is not None and data.GetArray(i).GetNumberOfComponents() == 1)

    def chooseDefaultNodeSets(self, parameterNode) -> None:
        """Pick the fixed node set (``chest_wall`` or ``pectoral``) and the contact set of a newly
        chosen mesh where it has them: ``skin`` (the plates touch the part between them and in
        front of the chest clearance), else every boundary node."""
        names = self.nodeSetNames(parameterNode.reference("inputMesh"))
        wasModifying = parameterNode.node.StartModify()
        parameterNode["fixedNodeSet"] = next((n for n in ("chest_wall", "pectoral") if n in names), "")
        parameterNode["contactNodeSet"] = "skin" if "skin" in names else "boundary"
        parameterNode.node.EndModify(wasModifying)

    @staticmethod
    def _nodeSet(mesh, name: str, what: str) -> np.ndarray:
        try:
            nodes = mesh.node_set(name)
        except ValueError as error:
            raise ValueError(f"{what} nodes: {error}") from None
        if len(nodes) == 0:
            raise ValueError(f"{what} nodes: the node set {name!r} is empty")
        return nodes

    def contactNodes(self, parameterNode, mesh) -> np.ndarray:
        """Node ids that may touch the plates: the ``contactNodeSet`` array, or every boundary node."""
        from BreastBiomechLib.mesh.tetmesh import boundary_nodes

        name = parameterNode["contactNodeSet"]
        if name in ("", "boundary"):
            return np.flatnonzero(boundary_nodes(mesh.tets, len(mesh.nodes)))
        return self._nodeSet(mesh, name, "contact")

    def placementNodes(self, parameterNode, mesh) -> np.ndarray:
        """The nodes the plates are placed against and must not start behind: ``breast_skin``
        where the mesh has it (BreastMesh meshes, whose skin also covers the chest), else the
        contact nodes."""
        if "breast_skin" in mesh.point_data:
            return self._nodeSet(mesh, "breast_skin", "breast skin")
        return self.contactNodes(parameterNode, mesh)

    def plateContacts(self, parameterNode, mesh, plates) -> np.ndarray:
        """The contact nodes the plates touch (BreastBiomechLib.solver.placement.plate_contacts):
        those that start between the plates; on a mesh with a chest wall the plates' flat faces
        end ``chestClearanceMm`` anterior to it (< 0: auto, the larger plate travel, at least
        5 mm) in a rounded edge of that radius, set on the plates. A plate that starts behind a
        placement node is refused."""
        from BreastBiomechLib.solver.placement import plate_contacts

        for plate in plates:
            plate.check_clear_of(mesh.nodes[self.placementNodes(parameterNode, mesh)])
        clearance = parameterNode["chestClearanceMm"]
        return plate_contacts(mesh, self.contactNodes(parameterNode, mesh), plates,
                              clearance if clearance >= 0 else None)

    @staticmethod
    def _elementTissues(mesh) -> np.ndarray:
        from BreastBiomechLib import labels

        if "tissue" in mesh.cell_data:
            return np.asarray(mesh.cell_data["tissue"]).astype(int).ravel()
        return np.full(len(mesh.tets), labels.FAT.label)  # a mesh without tissues is all one tissue

    def createDefaultMaterials(self, parameterNode):
        """A materials table with the starting values (BreastBiomechLib.solver.materials) of every
        tissue in the input mesh (all tissues if no mesh is chosen); chosen as the materials."""
        from BreastBiomechLib.mrml import materials_to_table_node
        from BreastBiomechLib.solver.materials import default_tissue_materials

        defaults = default_tissue_materials()
        meshNode = parameterNode.reference("inputMesh")
        present = set(self._elementTissues(self.inputMesh(parameterNode)).tolist()) if meshNode else set(defaults)
        unknown = sorted(present - set(defaults))
        if unknown:
            raise ValueError(f"the mesh's tissue array holds labels {unknown} that the label table does not know")
        node = materials_to_table_node({label: defaults[label] for label in sorted(present)}, self.scene,
                                       self.scene.GenerateUniqueName("Materials"))
        parameterNode.set_reference("materials", node)
        return node

    def materialTable(self, parameterNode, mesh) -> dict:
        """{tissue label: Material} of the tissues in the mesh, from the table (one row each)."""
        from BreastBiomechLib import labels
        from BreastBiomechLib.mrml import materials_from_table_node

        table = materials_from_table_node(parameterNode.reference("materials"))
        present = sorted(set(self._elementTissues(mesh).tolist()))
        missing = [t for t in present if t not in table]
        if missing:
            names = ", ".join(labels.tissue(t).name if t in labels.BY_LABEL else str(t) for t in missing)
            raise ValueError(f"the materials table has no row for {names}, which the mesh contains; add the rows "
                             "or press 'Default materials'")
        return {t: table[t] for t in present}

    def materials(self, parameterNode, mesh):
        """Per-element materials from the table (one row per tissue label in the mesh)."""
        from BreastBiomechLib.solver.materials import ElementMaterials

        return ElementMaterials.from_tissues(self._elementTissues(mesh), self.materialTable(parameterNode, mesh))

    def createCompressionPlates(self, parameterNode) -> list:
        """Two plates tangent to the mesh (its breast skin where it has one) on both sides of
        ``compressionAxis``, closing by
        ``compressionPercent`` of the thickness between them (``movingPlates``: both, first or
        second), as markups planes the user can move; the existing two are updated in place."""
        from BreastBiomechLib.mrml import plate_to_plane_node
        from BreastBiomechLib.solver.placement import axis_vector, compression_plates

        mesh = self.inputMesh(parameterNode)
        axis = parameterNode["compressionAxis"]
        plates = compression_plates(mesh, axis, parameterNode["compressionPercent"] / 100.0,
                                    self.contactNodes(parameterNode, mesh), names=self.PLATE_NAMES[axis],
                                    moving=parameterNode["movingPlates"],
                                    extent_nodes=self.placementNodes(parameterNode, mesh))
        direction = axis_vector(axis)
        across = mesh.nodes - np.outer(mesh.nodes @ direction, direction)
        size = 1.3 * float(np.max(np.ptp(across, axis=0)))
        existing = parameterNode.references("plates")
        nodes = []
        for i, plate in enumerate(plates):
            node = plate_to_plane_node(plate, self.scene, existing[i] if len(existing) == len(plates) else None,
                                       (size, size))
            node.SetName(plate.name)
            nodes.append(node)
        parameterNode.set_references("plates", nodes)
        return nodes

    @staticmethod
    def plateTravel(planeNode) -> float:
        """A plate's travel along its normal (mm, > 0 into the tissue)."""
        from BreastBiomechLib.mrml.markups import plate_travel

        return plate_travel(planeNode)

    def supportDescription(self, parameterNode) -> dict:
        """The chest-wall support as a case file's ``supports`` entry: the fixed node set, its
        kind (``chestWallMode``: fixed in the chosen directions, sliding or elastic on its surface,
        BreastBiomechLib.solver.supports.chest_wall_support), the springs (Pa/mm) and the anchor
        patches that stop the rigid motion the support leaves free."""
        name = parameterNode["fixedNodeSet"]
        if not name:
            raise ValueError("choose the fixed node set (e.g. chest_wall): without fixed nodes the breast "
                             "can move as a rigid body and there is no solution")
        kind = parameterNode["chestWallMode"]
        components = (parameterNode["fixLR"], parameterNode["fixAP"], parameterNode["fixSI"])
        if kind == "fixed" and not any(components):
            raise ValueError(f"choose at least one direction in which the {name!r} nodes are fixed")
        return {"nodes": name, "kind": kind, "components": [bool(c) for c in components],
                "normal_stiffness": float(parameterNode["chestWallNormalStiffness"]),
                "tangential_stiffness": float(parameterNode["chestWallTangentialStiffness"]),
                "anchor": bool(parameterNode["anchor"])}

    def caseDescription(self, parameterNode) -> tuple[dict, object]:
        """What a case file holds (BreastBiomechLib.io.cases, docs/solver.md), made from the
        scene's nodes: materials from the table, plates from the markups planes (contact nodes,
        rounded edges, each plate's friction), the chest-wall support, the skin layer (with
        ``skinModulusKPa`` > 0; its Poisson ratio the first material's), gravity and, with
        ``startUnloaded``, the reference state; and the mesh (TetMesh, LPS mm). The one input
        of the one model builder, :meth:`buildModel`, which `breastbiomech simulate` shares."""
        from BreastBiomechLib import labels
        from BreastBiomechLib.mrml import plate_from_plane_node

        mesh = self.inputMesh(parameterNode)
        planes = parameterNode.references("plates")
        if not planes:
            raise ValueError("no plates: press 'Place plates' (or add markups planes as plates)")
        frictions = [parameterNode["plateFriction1"], parameterNode["plateFriction2"]]
        if len(planes) > len(frictions):
            raise ValueError(f"the panel sets the friction of two plates; this model has {len(planes)}: write a "
                             "case file for more (docs/solver.md)")
        centre = mesh.nodes.mean(axis=0)
        plates = [plate_from_plane_node(node, [], towards=centre) for node in planes]
        contacts = self.plateContacts(parameterNode, mesh, plates)
        table = self.materialTable(parameterNode, mesh)
        if "tissue" in mesh.cell_data:
            materials = {labels.tissue(label).name: self._materialEntry(m) for label, m in table.items()}
        else:
            materials = {"default": self._materialEntry(table[labels.FAT.label])}
        gravity = self.GRAVITY[parameterNode["gravity"]]
        description = {
            "materials": materials,
            "supports": [self.supportDescription(parameterNode)],
            "plates": [{"name": p.name, "point": p.point.tolist(), "normal": p.normal.tolist(),
                        "displacement": p.displacement.tolist(), "slaves": contacts.tolist(),
                        "friction": float(mu), **({"edge": p.edge.to_dict()} if p.edge else {})}
                       for p, mu in zip(plates, frictions)],
            "gravity": list(gravity or (0.0, 0.0, 0.0)),
            "formulation": parameterNode["formulation"], "damping": float(parameterNode["damping"]),
            "total_time": float(parameterNode["totalTime"]), "settle_time": float(parameterNode["settleTime"]),
            "solver": {"method": parameterNode["method"]},
        }
        if parameterNode["method"] == "relaxation":
            description["solver"]["tolerance_mm"] = float(parameterNode["tolerance"])
        elif parameterNode["stopWhenSettled"]:
            description["solver"]["steady_state_mm"] = float(parameterNode["tolerance"])
        if parameterNode["skinModulusKPa"] > 0:
            skin_nodes = "skin" if "skin" in mesh.point_data else self.contactNodes(parameterNode, mesh).tolist()
            description["skin"] = {"E": 1e3 * float(parameterNode["skinModulusKPa"]),
                                   "nu": float(materials[next(iter(materials))]["nu"]),
                                   "thickness_mm": float(parameterNode["skinThicknessMm"]), "nodes": skin_nodes}
        if parameterNode["startUnloaded"]:
            if gravity is None:
                raise ValueError("starting from the unloaded shape needs the gravity the mesh was imaged under: "
                                 "choose its direction")
            description["reference_state"] = {"imaged_gravity": list(gravity)}
        return description, mesh

    @staticmethod
    def _materialEntry(material) -> dict:
        return {"E": material.E, "nu": material.nu, "eta": material.eta, "fibre": list(material.fibre),
                "density": material.density, "prony": [list(term) for term in material.prony]}

    def buildCase(self, parameterNode):
        """The solver Model and SolverSettings of the current choices (LPS mm, Pa, s): the scene's
        case description through the case files' builder (BreastBiomechLib.io.cases.case_from_dict)."""
        from pathlib import Path

        from BreastBiomechLib.io.cases import case_from_dict

        description, mesh = self.caseDescription(parameterNode)
        return case_from_dict(description, mesh, Path(parameterNode.reference("inputMesh").GetName()))

    def buildModel(self, parameterNode):
        """The solver Model of the current choices (see :meth:`buildCase`)."""
        return self.buildCase(parameterNode)[0]

    # -- device ----------------------------------------------------------------------------------

    @staticmethod
    def cudaAvailable() -> bool:
        import warp as wp

        wp.init()
        return wp.get_cuda_device_count() > 0

    @staticmethod
    def resolveDevice(choice: str) -> str:
        """"cuda" or "cpu" for the choice "auto" (the GPU when present), "cuda" or "cpu"."""
        return resolve_device(choice)

    def deviceAtOpen(self) -> str:
        """What the panel says about the device before anything starts warp: the description once
        warp has been started in this session (by a Run or another module), else that the first
        Run looks for the GPU."""
        import sys

        contexts = (sys.modules.get(name) for name in ("warp._src.context", "warp.context"))  # warp >= 1.10, older
        if any(getattr(context, "runtime", None) is not None for context in contexts):
            return self.deviceDescription()
        return _("the GPU when there is one, else the CPU: looked up at the first Run (which starts warp)")

    def deviceDescription(self, choice: str = "auto") -> str:
        """What the solver will run on, for the panel, e.g. "GPU: NVIDIA H100 80GB HBM3"."""
        import warp as wp

        device = self.resolveDevice(choice)
        if device == "cuda":
            return f"GPU: {wp.get_device('cuda').name}"
        return "CPU (warp's CPU device)" + ("" if self.cudaAvailable() else "; no CUDA GPU found")

    # -- run -------------------------------------------------------------------------------------

    def run(self, parameterNode, progress=None) -> dict:
        """Solve the model (a physical-time run stops early once settled to ``tolerance`` mm when
        ``stopWhenSettled``) and put the results into the scene: the deformed mesh (output mesh node,
        created if none is chosen; point arrays ``displacement`` (mm, RAS) and
        ``displacement_magnitude``), the history table and the plate-force and energy charts.

        ``progress(fraction, message)`` is called as the solve advances; returning False cancels
        it, and a cancelled run leaves the earlier results untouched. Returns a dict with the
        ``solution`` (library Solution, LPS), the ``model``, the ``device`` and a ``summary``."""
        from dataclasses import replace

        from BreastBiomechLib.solver.run_case import run_case

        if parameterNode["method"] not in ("relaxation", "physical"):
            raise ValueError(f"method must be relaxation or physical, not {parameterNode['method']!r}")
        device = self.resolveDevice(parameterNode["device"])
        model, settings = self.buildCase(parameterNode)
        settings = replace(settings, device=device)
        relaxation = settings.relaxation if settings.method == "relaxation" else None
        what = "dynamic relaxation" if relaxation else "explicit dynamics"
        imaged = model

        def report(fraction):
            return progress(fraction, f"{what} on {device}: {fraction:.0%} of the step budget")

        def reference_report(iteration, residual):
            progress(0.0, f"estimating the unloaded (stress-free) shape: iteration {iteration}, largest node "
                          f"mismatch {residual:.3f} mm")

        if progress is not None:
            progress(0.0, "estimating the unloaded (stress-free) shape" if settings.unloaded is not None
                     else f"{what} on {device}: starting")
        result = run_case(model, settings, progress=report if progress is not None else None,
                          reference_progress=reference_report if progress is not None else None,
                          ke_ie_limit=self.KE_IE_LIMIT)
        solution, model = result.solution, result.model
        # displacements from the mesh as imaged, not from its unloaded shape
        solution.displacement = result.displacement
        summary = self.summaryText(solution, model, device, relaxation is not None)
        logging.info("BreastSimulation: %s", summary)
        if solution.status != "cancelled":
            self._writeResults(parameterNode, imaged, solution, relaxation is not None)
        if progress is not None:
            progress(1.0, solution.status)
        return {"solution": solution, "model": model, "device": device, "summary": summary}

    # -- run out of Slicer's process -------------------------------------------------------------

    def writeCase(self, parameterNode, folder) -> str:
        """The current choices as a case file: ``folder``/case.json with the mesh beside it
        (mesh.vtu), the format `breastbiomech simulate` reads (docs/solver.md). Returns its path."""
        import json
        from pathlib import Path

        from BreastBiomechLib.io.atomic import write_text_atomically
        from BreastBiomechLib.io.meshes import write_vtu

        if parameterNode["method"] not in ("relaxation", "physical"):
            raise ValueError(f"method must be relaxation or physical, not {parameterNode['method']!r}")
        description, mesh = self.caseDescription(parameterNode)
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        write_vtu(folder / "mesh.vtu", mesh)
        path = folder / "case.json"
        write_text_atomically(path, json.dumps({**description, "mesh": "mesh.vtu"}, indent=1))
        return str(path)

    def startRun(self, parameterNode, folder=None):
        """Start the solve in a process of its own (`breastbiomech simulate`, see
        BreastBiomechCommon.worker): the case written to ``folder`` (default: a new folder in
        Slicer's temporary folder), the results to ``folder``/result. Returns the running
        :class:`~BreastBiomechCommon.worker.CommandWorker`: poll it, and once it has ended
        :meth:`finishRun` puts its results into the scene. Bad choices are refused here, before
        anything starts."""
        import os
        import tempfile

        from BreastBiomechCommon.worker import CommandWorker

        if parameterNode["device"] not in ("auto", "cuda", "cpu"):
            raise ValueError(f"device must be auto, cuda or cpu, not {parameterNode['device']!r}")
        if folder is None:
            root = slicer.app.temporaryPath if IN_SLICER_APPLICATION else None
            folder = tempfile.mkdtemp(prefix="BreastSimulation-", dir=root)
        case = self.writeCase(parameterNode, folder)
        device = [] if parameterNode["device"] == "auto" else ["--device", parameterNode["device"]]
        return CommandWorker(["simulate", case, "--out", os.path.join(str(folder), "result"), *device],
                             folder=str(folder)).start()

    def finishRun(self, parameterNode, worker) -> dict:
        """The results of an ended :meth:`startRun` into the scene, as :meth:`run` puts them (a
        solve that did not complete, e.g. inverted elements, shows where it stopped, with its
        status). A cancelled or crashed worker leaves the earlier results untouched and raises
        RuntimeError with its reason. Returns :meth:`run`'s dict."""
        import os

        from BreastBiomechLib.io.cases import read_case
        from BreastBiomechLib.io.solutions import read_solution

        if worker.running:
            raise RuntimeError("the simulation is still running: wait for it or cancel it")
        if worker.cancelled:
            raise RuntimeError("the simulation was cancelled; the earlier results are unchanged")
        result = os.path.join(worker.folder, "result")
        if worker.returncode not in (0, 1) or not os.path.isfile(os.path.join(result, "solution.json")):
            raise RuntimeError(worker.error or "the simulation wrote no results")
        solution, _summary = read_solution(result)
        model, settings = read_case(os.path.join(worker.folder, "case.json"))
        relaxation = settings.method == "relaxation"
        device = worker.outputs().get("device") or parameterNode["device"]
        summary = self.summaryText(solution, model, device, relaxation)
        logging.info("BreastSimulation: %s", summary)
        self._writeResults(parameterNode, model, solution, relaxation)
        return {"solution": solution, "model": model, "device": device, "summary": summary}

    def _writeResults(self, parameterNode, model, solution, relaxation: bool) -> None:
        from BreastBiomechLib.mesh.tetmesh import TetMesh
        from BreastBiomechLib.mrml import columns_to_table_node, plot_chart_node, tetmesh_to_model_node

        mesh, u = model.mesh, solution.displacement
        deformed = TetMesh(mesh.nodes + u, mesh.tets,
                           point_data={**mesh.point_data, "displacement": u,
                                       "displacement_magnitude": np.linalg.norm(u, axis=1)},
                           cell_data=dict(mesh.cell_data))
        name = self.scene.GenerateUniqueName(f"{parameterNode.reference('inputMesh').GetName()}_deformed")
        output = tetmesh_to_model_node(deformed, self.scene, name, node=parameterNode.reference("outputMesh"))
        parameterNode.set_reference("outputMesh", output)
        display = output.GetDisplayNode()
        if display is not None:
            display.SetActiveScalar("displacement_magnitude", vtk.vtkAssignAttribute.POINT_DATA)
            display.SetAndObserveColorNodeID("vtkMRMLColorTableNodeRainbow")
            display.SetScalarRangeFlag(display.UseDataScalarRange)
            display.SetScalarVisibility(True)

        columns = self.historyColumns(model, solution, relaxation)
        history = columns_to_table_node(columns, self.scene, self.scene.GenerateUniqueName("SimulationHistory"),
                                        node=parameterNode.reference("history"))
        parameterNode.set_reference("history", history)
        x = next(iter(columns))
        forces = [c for c in columns if c.endswith("force (N)")]
        energies = ["kinetic energy (J)", "internal energy (J)"]
        parameterNode.set_reference("forceChart", plot_chart_node(
            history, x, forces, self.scene, "Plate forces", "force (N)", node=parameterNode.reference("forceChart")))
        parameterNode.set_reference("energyChart", plot_chart_node(
            history, x, energies, self.scene, "Energies", "energy (J)", node=parameterNode.reference("energyChart")))

    @staticmethod
    def historyColumns(model, solution, relaxation: bool) -> dict:
        """The sampled history as table columns: time (s; iterations for dynamic relaxation, whose
        time is fictitious), kinetic and internal energy (J), and each plate's normal force on the
        tissue (N, > 0 when it presses)."""
        h = solution.history
        x = ("iteration", np.rint(h["time"] / solution.time_step)) if relaxation else ("time (s)", h["time"])
        columns = {x[0]: x[1], "kinetic energy (J)": h["kinetic"], "internal energy (J)": h["internal"]}
        forces = np.asarray(h["plate_forces"]).reshape(len(h["time"]), len(model.loading.plates), 3)
        for i, plate in enumerate(model.loading.plates):
            columns[f"{plate.name} force (N)"] = forces[:, i] @ plate.normal
        return columns

    def summaryText(self, solution, model, device: str, relaxation: bool) -> str:
        forces = ", ".join(f"{p.name} {solution.plate_forces[i] @ p.normal:.3g} N"
                           for i, p in enumerate(model.loading.plates))
        largest = float(np.linalg.norm(solution.displacement, axis=1).max())
        notes = "".join(f"\nSupport: {note}" for note in model.loading.notes)
        return (f"{solution.status}: {solution.message}\n{solution.steps} steps in {solution.wall_time:.2f} s on "
                f"{device}; largest displacement {largest:.2f} mm; plate forces {forces}{notes}\n"
                + self.energyVerdict(solution, relaxation))

    def energyVerdict(self, solution, relaxation: bool) -> str:
        """The seed's quasi-static check: kinetic / internal energy at the end of loading < 5 %."""
        if relaxation:
            return (f"Static equilibrium by dynamic relaxation (estimated error {solution.estimated_error_mm:.3g} mm); "
                    "the KE/IE criterion does not apply to its fictitious dynamics.")
        ratio = solution.ke_ie_at_end_of_loading
        if not np.isfinite(ratio):
            return "KE/IE: the end of loading was not reached."
        if ratio < self.KE_IE_LIMIT:
            return f"KE/IE at the end of loading {ratio:.2%} < {self.KE_IE_LIMIT:.0%}: quasi-static."
        return (f"KE/IE at the end of loading {ratio:.1%} >= {self.KE_IE_LIMIT:.0%}: inertia is not negligible; "
                "lengthen the loading time or raise the damping.")

    def showResults(self, parameterNode) -> None:
        """Show the deformed mesh and the plate-force chart (application only)."""
        if not IN_SLICER_APPLICATION:
            return
        input_node = parameterNode.reference("inputMesh")
        if input_node is not None and input_node.GetDisplayNode() is not None:
            input_node.GetDisplayNode().SetOpacity(0.2)
        slicer.modules.plots.logic().ShowChartInLayout(parameterNode.reference("forceChart"))


#
# Test (runs inside Slicer: Reload and Test; the thorough checks run headless in Testing/)
#


class BreastSimulationTest(ModuleTestMixin, ScriptedLoadableModuleTest):
    REQUIRES = tuple(DEPENDENCIES)

    def test_compress_hemi_ellipsoid(self):
        from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
        from BreastBiomechLib.mrml import tetmesh_to_model_node

        self.delayDisplay("Compressing a coarse hemi-ellipsoid by 20 %")
        logic = BreastSimulationLogic()
        p = logic.getParameterNode()
        p.set_reference("inputMesh", tetmesh_to_model_node(hemi_ellipsoid_mesh((50, 40, 45), 10.0),
                                                           slicer.mrmlScene, "Breast"))
        logic.chooseDefaultNodeSets(p)
        p["compressionPercent"] = 20.0
        logic.createDefaultMaterials(p)
        logic.createCompressionPlates(p)
        result = logic.run(p)
        self.assertEqual(result["solution"].status, "completed")
        self.assertGreater(result["solution"].plate_forces[0] @ result["model"].loading.plates[0].normal, 0.0)
        logic.showResults(p)
        self.delayDisplay("Test passed")
