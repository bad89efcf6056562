"""BreastMesh: from a tissue segmentation to a tetrahedral breast mesh ready for simulation.

Choose the segmentation (segments named after the tissues of the label table: fat, glandular,
muscle, tumour, skin), the element size and the quality bounds; get a model node holding the
tetrahedral mesh coloured by tissue (cell arrays: tissue, tissue fractions, quality measures;
point arrays: the loading node sets chest_wall, fov_cut, skin, breast_skin, nipple), the
quality report and tissue representation as tables, and the dihedral-angle histogram as a plot.

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
                                 ensure_library_importable)

ensure_library_importable()

DEPENDENCIES = ["numpy", "scipy", "SimpleITK", "tetgen"]
RED_SLICE = "vtkMRMLSliceNodeRed"  # the application's red slice node, where the mesh display is clipped


class BreastMesh(ModuleBase):
    def __init__(self, parent):
        ModuleBase.__init__(self, parent)
        self.parent.title = _("Breast Mesh")
        self.parent.helpText = _("""
Tetrahedral finite-element mesh of the breast from a tissue segmentation: body surface, TetGen mesh
refined by points of each tissue surface, tissue per element by voxel majority, the seed's ABAQUS
quality criteria and the loading node sets (chest wall, skin, nipple). See docs/meshing.md of the
<a href='https://github.com/BreastBiomech/BreastBiomech'>project</a>.<p><b>Licence of TetGen</b>: meshing
uses TetGen through the tetgen Python package, which is licensed under the GNU Affero General Public
License (AGPL v3). The first <i>Apply</i> offers to install it into Slicer's Python; by installing it
you accept its licence. BreastBiomech itself is BSD-licensed and does not bundle TetGen.</p>
""")
        self.parent.acknowledgementText = _("""
Method after Han et al. 2012, Phys. Med. Biol. 57:455; meshing by TetGen (Si 2015) through the tetgen
Python package; surfaces by VTK.
""")


class BreastMeshWidget(ModuleWidgetBase):
    def connectGUI(self):
        self.connectLogic(self.ui.clipCheckBox.toggled,
                          lambda parameterNode, checked: self.logic.applyClipping(parameterNode))

    def showParameters(self, p):
        self.ui.interfaceEdgeSpinBox.enabled = p["refineInterfaces"]
        self.ui.qualityTableView.setMRMLTableNode(p.reference("qualityTable"))
        self.ui.tissueTableView.setMRMLTableNode(p.reference("tissueTable"))
        self.ui.applyButton.enabled = p.reference("inputSegmentation") is not None

    def onApplyButton(self):
        if not dependencies_ready(DEPENDENCIES, _("Breast Mesh")):
            return
        self.ui.applyButton.enabled = False
        self.ui.progressBar.value = 0

        def report(fraction, message):
            self.ui.progressBar.value = int(100 * fraction)
            self.ui.progressBar.setFormat(f"{message} (%p%)")
            slicer.app.processEvents()

        try:
            with slicer.util.tryWithErrorDisplay(_("Meshing failed."), waitCursor=True):
                result = self.logic.run(self._parameterNode, progress=report)
                self.ui.statusLabel.text = self.logic.summaryText(result)
                self.logic.showResults(self._parameterNode)
        finally:
            self.ui.applyButton.enabled = True


class BreastMeshLogic(ModuleLogicBase):
    """Segmentation node -> label map -> BreastBiomechLib.mesh.mesh_labels -> model, table and plot
    nodes. No Qt: runs in Slicer and headless (slicer-core wheel).

    Lengths in mm, angles in degrees; the mesh is stored in the scene in RAS (the library's LPS
    converted by BreastBiomechLib.mrml). ``scene`` defaults to ``slicer.mrmlScene``."""

    MODULE_NAME = "BreastMesh"
    DEFAULTS = {"edgeMm": 3.0, "interfaceEdgeMm": 0.0, "refineInterfaces": True, "blurMm": 0.8,
                "minRadiusEdge": 1.5, "minDihedralDeg": 12.0, "clip": False}
    ROLES = ("inputSegmentation", "nipple", "outputMesh", "qualityTable", "tissueTable", "dihedralTable",
             "dihedralChart", "clipNode")

    # -- inputs ----------------------------------------------------------------------------------

    def settings(self, parameterNode):
        """The library MeshSettings of the current choices (``interfaceEdgeMm`` 0: the element size)."""
        from BreastBiomechLib.mesh.from_labels import MeshSettings

        p = parameterNode
        if not p["edgeMm"] > 0:
            raise ValueError(f"the element size must be positive, not {p['edgeMm']:g} mm")
        if p["interfaceEdgeMm"] < 0:
            raise ValueError("the interface point spacing must be positive, or 0 for the element size")
        if not 1.0 < p["minRadiusEdge"]:
            raise ValueError(f"the radius-edge bound must exceed 1 (TetGen needs > 1; 1.5 is usual), "
                             f"not {p['minRadiusEdge']:g}")
        if not 0.0 <= p["minDihedralDeg"] < 20.0:
            raise ValueError(f"the minimum dihedral angle must lie in [0, 20) degrees (TetGen seldom terminates "
                             f"above ~18), not {p['minDihedralDeg']:g}")
        return MeshSettings(edge_mm=p["edgeMm"], interface_edge_mm=p["interfaceEdgeMm"] or None,
                            refine_interfaces=p["refineInterfaces"], blur_mm=p["blurMm"],
                            min_radius_edge=p["minRadiusEdge"], min_dihedral_deg=p["minDihedralDeg"])

    def labelImage(self, parameterNode):
        """The input segmentation as a label image of the label table (SimpleITK, LPS)."""
        from BreastBiomechLib.mrml import labels_from_segmentation_node

        node = parameterNode.reference("inputSegmentation")
        if node is None:
            raise ValueError("choose the input segmentation (segments named fat, glandular, muscle, tumour, skin)")
        if node.GetSegmentation().GetNumberOfSegments() == 0:
            raise ValueError(f"the segmentation {node.GetName()!r} has no segments; segment the breast first "
                             "(BreastSegmentation module or Segment Editor)")
        return labels_from_segmentation_node(node, self.scene)

    @staticmethod
    def nipplePosition(parameterNode):
        """The nipple (LPS mm) from the nipple markups: the point labelled 'nipple', else the only
        point; None when no markups node is chosen (the mesh then takes the most anterior skin node)."""
        from BreastBiomechLib.mrml import landmarks_from_markups_node

        node = parameterNode.reference("nipple")
        if node is None:
            return None
        marks = landmarks_from_markups_node(node)
        if "nipple" in marks.labels:
            return marks.positions[marks.labels.index("nipple")]
        if len(marks.labels) == 1:
            return marks.positions[0]
        raise ValueError(f"the markups {node.GetName()!r} hold {len(marks.labels)} points and none is labelled "
                         "'nipple'; label the nipple point 'nipple' or keep a single point")

    # -- run -------------------------------------------------------------------------------------

    def run(self, parameterNode, progress=None):
        """Mesh the segmentation and put the results into the scene (see :meth:`writeResults`).

        ``progress(fraction, message)`` is called between the stages. Returns the library's
        BreastMesh (LPS), whose ``summary()`` is the JSON report the CLI writes."""
        from BreastBiomechLib.mesh.from_labels import mesh_labels

        settings = self.settings(parameterNode)
        nipple = self.nipplePosition(parameterNode)
        if progress is not None:
            progress(0.0, "exporting the segmentation")
        labels = self.labelImage(parameterNode)
        result = mesh_labels(labels, settings, nipple_mm=nipple, progress=progress)
        self.writeResults(parameterNode, result)
        logging.info("BreastMesh: %s", self.summaryText(result))
        return result

    def writeResults(self, parameterNode, result) -> None:
        """The mesh as the output model node (created if none is chosen; coloured by tissue), the
        quality table (ABAQUS criteria: count and percent failing, and the extremes), the tissue
        table (elements per tissue, Dice against the label map, volumes) and the dihedral-angle
        histogram (table and bar chart). A second run refills the same nodes."""
        from BreastBiomechLib.mrml import columns_to_table_node, plot_chart_node, tetmesh_to_model_node

        p = parameterNode
        segmentation = p.reference("inputSegmentation")
        base = segmentation.GetName() if segmentation is not None else "Breast"
        node = tetmesh_to_model_node(result.mesh, self.scene, self.scene.GenerateUniqueName(f"{base}_mesh"),
                                     node=p.reference("outputMesh"))
        p.set_reference("outputMesh", node)
        self._colourByTissue(node)
        self.applyClipping(p)

        def table(role, name, columns):
            p.set_reference(role, columns_to_table_node(columns, self.scene, self.scene.GenerateUniqueName(name),
                                                        node=p.reference(role)))

        table("qualityTable", "MeshQuality", self.qualityColumns(result.quality))
        table("tissueTable", "MeshTissues", self.tissueColumns(result))
        bins_deg = np.asarray(result.quality.summary()["dihedral_histogram"]["bins_deg"])
        smallest, largest = result.quality.dihedral_histogram()
        table("dihedralTable", "MeshDihedralAngles", {
            "dihedral angle (deg)": 0.5 * (bins_deg[:-1] + bins_deg[1:]),
            "elements (smallest angle)": smallest, "elements (largest angle)": largest})
        p.set_reference("dihedralChart", plot_chart_node(
            p.reference("dihedralTable"), "dihedral angle (deg)", ["elements (smallest angle)",
                                                                   "elements (largest angle)"],
            self.scene, "Dihedral angles", "elements", node=p.reference("dihedralChart"), bars=True))

    def _colourByTissue(self, node) -> None:
        from BreastBiomechLib.mrml import tissue_color_table_node

        display = node.GetDisplayNode()
        if display is None:
            node.CreateDefaultDisplayNodes()
            display = node.GetDisplayNode()
        colours = tissue_color_table_node(self.scene)
        display.SetActiveScalar("tissue", vtk.vtkAssignAttribute.CELL_DATA)
        display.SetAndObserveColorNodeID(colours.GetID())
        display.SetScalarRangeFlag(display.UseColorNodeScalarRange)
        display.SetScalarVisibility(True)
        display.SetEdgeVisibility(True)

    def applyClipping(self, parameterNode) -> None:
        """Clip the mesh display at the red slice (``clip``), keeping whole cells so the elements
        inside can be inspected; the clip node (clipping by the red slice node, negative side) is
        made on first use."""
        node = parameterNode.reference("outputMesh")
        if node is None or node.GetDisplayNode() is None:
            return
        clip = parameterNode.reference("clipNode")
        if clip is None:
            clip = self.scene.AddNewNodeByClass("vtkMRMLClipNode", self.scene.GenerateUniqueName("MeshClip"))
            clip.SetClippingMethod(clip.WholeCells)
            clip.AddAndObserveClippingNodeID(RED_SLICE)
            clip.SetClippingNodeState(RED_SLICE, clip.ClipNegativeSpace)
            parameterNode.set_reference("clipNode", clip)
        display = node.GetDisplayNode()
        display.SetAndObserveClipNodeID(clip.GetID())
        display.SetClipping(parameterNode["clip"])

    # -- reports ---------------------------------------------------------------------------------

    @staticmethod
    def qualityColumns(quality) -> dict:
        """The seed's ABAQUS criteria as rows (criterion, failing count and percent) and the
        extremes of each measure."""
        summary = quality.summary()
        rows = [(name.replace("_", " "), row["criterion"], row["count"], row["percent"])
                for name, row in summary["failing"].items()]
        extremes = [("smallest shape factor", summary["shape_factor_min"]),
                    ("smallest face angle (deg)", summary["face_angle_min_deg"]),
                    ("largest face angle (deg)", summary["face_angle_max_deg"]),
                    ("largest aspect ratio", summary["aspect_ratio_max"]),
                    ("smallest dihedral angle (deg)", summary["dihedral_min_deg"]),
                    ("largest dihedral angle (deg)", summary["dihedral_max_deg"])]
        return {"measure": np.array([r[0] for r in rows] + [e[0] for e in extremes], dtype=object),
                "criterion": np.array([r[1] for r in rows] + [""] * len(extremes), dtype=object),
                "failing elements": np.array([r[2] for r in rows] + [np.nan] * len(extremes)),
                "failing (%)": np.array([r[3] for r in rows] + [np.nan] * len(extremes)),
                "value": np.array([np.nan] * len(rows) + [e[1] for e in extremes])}

    @staticmethod
    def tissueColumns(result) -> dict:
        """Per tissue: elements, Dice of the element tissues against the label map, and the
        volumes (cm^3) of the label and of its elements."""
        counts = result.assignment.counts()  # in label-table order
        names = list(counts)
        rep = result.representation
        return {"tissue": np.array(names, dtype=object),
                "elements": np.array([counts[n] for n in names]),
                "Dice": np.array([rep[n]["dice"] if n in rep else np.nan for n in names]),
                "label volume (cm3)": np.array([rep[n]["label_cm3"] if n in rep else np.nan for n in names]),
                "element volume (cm3)": np.array([rep[n]["elements_cm3"] if n in rep else np.nan for n in names])}

    @staticmethod
    def summaryText(result) -> str:
        summary = result.summary()
        failing = summary["quality"]["failing"]["any"]
        lines = [f"{summary['nodes']} nodes, {summary['elements']} tetrahedra, {summary['volume_cm3']:.0f} cm³ "
                 f"in {summary['seconds']['total']:.1f} s",
                 "Elements: " + ", ".join(f"{k} {v}" for k, v in summary["elements_per_tissue"].items()),
                 f"Quality: {failing['count']} elements ({failing['percent']:.3f} %) fail the seed's criteria; "
                 f"smallest dihedral angle {summary['quality']['dihedral_min_deg']:.1f}°"]
        lines += [f"Note: {note}" for note in summary["notes"]]
        return "\n".join(lines)

    def showResults(self, parameterNode) -> None:
        """Show the mesh and the dihedral-angle histogram, hide the segmentation (application only)."""
        if not IN_SLICER_APPLICATION:
            return
        segmentation = parameterNode.reference("inputSegmentation")
        if segmentation is not None and segmentation.GetDisplayNode() is not None:
            segmentation.GetDisplayNode().SetVisibility3D(False)
        slicer.modules.plots.logic().ShowChartInLayout(parameterNode.reference("dihedralChart"))


#
# Test (runs inside Slicer: Reload and Test; the thorough checks run headless in Testing/)
#


class BreastMeshTest(ModuleTestMixin, ScriptedLoadableModuleTest):
    REQUIRES = tuple(DEPENDENCIES)

    def test_mesh_phantom(self):
        from BreastBiomechLib.mrml import labels_to_segmentation_node
        from BreastBiomechLib.phantom import PhantomParameters, generate_phantom

        self.delayDisplay("Meshing a 400 cm³ phantom at 5 mm")
        case = generate_phantom(PhantomParameters(volume_cm3=400.0))
        logic = BreastMeshLogic()
        p = logic.getParameterNode()
        p.set_reference("inputSegmentation", labels_to_segmentation_node(case.labels, slicer.mrmlScene))
        p["edgeMm"] = 5.0
        result = logic.run(p)
        self.assertGreater(len(result.mesh.tets), 1000)
        self.assertEqual(p.reference("outputMesh").GetUnstructuredGrid().GetNumberOfCells(), len(result.mesh.tets))
        logic.showResults(p)
        self.delayDisplay("Test passed")
