"""The BreastMesh module's Logic against a real MRML scene (slicer-core, headless).

The input goes through the nodes a user has (a segmentation node made from a label map, a nipple
point list) and the outputs are checked against the label map and the library: a lost RAS/LPS
conversion, a dropped node set or a table that disagrees with the mesh shows up here."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("slicer")
import BreastMesh  # noqa: E402  (BreastBiomech/ is on the test path)
import BreastSimulation  # noqa: E402
from meshing_fixtures import TUMOUR_CENTRE, breast_labels  # noqa: E402

from BreastBiomechLib import labels as lt  # noqa: E402
from BreastBiomechLib.landmarks import Landmarks  # noqa: E402
from BreastBiomechLib.mrml import (  # noqa: E402
    frames,
    labels_to_segmentation_node,
    landmarks_to_markups_node,
    tetmesh_from_model_node,
)

pytestmark = pytest.mark.mrml


@pytest.fixture(scope="module")
def labels():
    return breast_labels(spacing=(1.5, 1.5, 2.5))


def _set_up(scene, labels, edge_mm=5.0):
    logic = BreastMesh.BreastMeshLogic(scene)
    p = logic.getParameterNode()
    p.set_reference("inputSegmentation", labels_to_segmentation_node(labels, scene, "Tissues"))
    p["edgeMm"] = edge_mm
    return logic, p


def test_mesh_from_segmentation(scene, labels):
    logic, p = _set_up(scene, labels)
    nipple_lps = np.array([0.0, -32.0, 0.0])  # the front of the half ellipsoid
    p.set_reference("nipple", landmarks_to_markups_node(Landmarks(nipple_lps[None], ["nipple"]), scene, "Nipple"))
    stages = []
    result = logic.run(p, progress=lambda fraction, message: stages.append((fraction, message)))
    assert stages[0] == (0.0, "exporting the segmentation") and stages[-1] == (1.0, "done")
    assert [f for f, _ in stages] == sorted(f for f, _ in stages)

    # the model node holds the library's mesh in RAS, with every cell and point array
    node = p.reference("outputMesh")
    assert node.GetName() == "Tissues_mesh"
    back = tetmesh_from_model_node(node)
    np.testing.assert_allclose(back.nodes, result.mesh.nodes, atol=1e-4)
    np.testing.assert_array_equal(back.tets, result.mesh.tets)
    grid = node.GetUnstructuredGrid()
    np.testing.assert_allclose(np.array(grid.GetPoint(0)), frames.flip(result.mesh.nodes[:1])[0], atol=1e-4)
    assert set(back.point_data) == {"chest_wall", "fov_cut", "skin", "breast_skin", "nipple"}
    assert {"tissue", "fraction_fat", "quality_fails", "quality_min_dihedral_deg"} <= set(back.cell_data)
    assert set(np.unique(back.cell_data["tissue"])) == {lt.FAT.label, lt.GLANDULAR.label, lt.MUSCLE.label,
                                                        lt.TUMOUR.label}
    # the nipple node is the skin node nearest the chosen point (LPS in the library)
    nipple = np.flatnonzero(back.point_data["nipple"])
    skin = back.nodes[back.point_data["skin"] > 0]
    assert len(nipple) == 1
    assert np.linalg.norm(back.nodes[nipple[0]] - nipple_lps) == pytest.approx(
        np.linalg.norm(skin - nipple_lps, axis=1).min())
    # the tumour is where the label map has it: its elements' centroid within 2 mm of the sphere's centre
    tumour = back.cell_data["tissue"] == lt.TUMOUR.label
    centroid = (back.nodes[back.tets[tumour]].mean(axis=1) * back.volumes[tumour, None]).sum(0) / back.volumes[tumour].sum()
    assert np.linalg.norm(centroid - TUMOUR_CENTRE) < 2.0

    # coloured by tissue with the label table's colours
    display = node.GetDisplayNode()
    assert display.GetActiveScalarName() == "tissue" and display.GetScalarVisibility()
    colours = display.GetColorNode()
    assert colours.GetColorName(lt.TUMOUR.label) == "tumour"
    rgba = [0.0] * 4
    colours.GetColor(lt.GLANDULAR.label, rgba)
    assert rgba[:3] == pytest.approx(lt.GLANDULAR.color, abs=1 / 255)  # stored as 8 bits

    # quality table: one row per criterion with the report's counts
    quality = p.reference("qualityTable")
    rows = {quality.GetCellText(r, 0): r for r in range(quality.GetNumberOfRows())}
    failing = result.quality.failing()
    for name in ("shape factor", "face angle", "aspect ratio", "any"):
        count = quality.GetTable().GetValueByName(rows[name], "failing elements").ToDouble()
        assert count == failing[name.replace(" ", "_")].sum()
    smallest = quality.GetTable().GetValueByName(rows["smallest dihedral angle (deg)"], "value").ToDouble()
    assert smallest == pytest.approx(result.quality.min_dihedral_deg.min(), rel=1e-6)

    # tissue table: element counts and Dice of every tissue (a 5 mm tumour at 5 mm elements: ~0.77)
    tissues = p.reference("tissueTable")
    table = {tissues.GetCellText(r, 0): r for r in range(tissues.GetNumberOfRows())}
    assert set(table) == {"fat", "glandular", "muscle", "tumour"}
    for name, row in table.items():
        assert tissues.GetTable().GetValueByName(row, "elements").ToInt() == np.count_nonzero(
            back.cell_data["tissue"] == lt.BY_NAME[name].label)
        dice = tissues.GetTable().GetValueByName(row, "Dice").ToDouble()
        assert dice == pytest.approx(result.representation[name]["dice"]) and dice > 0.7

    # dihedral histogram: bar chart over a table whose counts add up to the elements
    chart = p.reference("dihedralChart")
    assert chart.GetNumberOfPlotSeriesNodes() == 2
    series = chart.GetNthPlotSeriesNode(0)
    assert series.GetPlotType() == series.PlotTypeBar
    histogram = p.reference("dihedralTable").GetTable()
    counts = [histogram.GetValueByName(r, "elements (smallest angle)").ToDouble()
              for r in range(histogram.GetNumberOfRows())]
    assert sum(counts) == len(back.tets)

    # the summary names sizes, quality and tissues
    text = logic.summaryText(result)
    assert f"{len(back.tets)} tetrahedra" in text and "fail the seed's criteria" in text and "tumour" in text

    # clipping keeps whole cells at the red slice; toggled through the parameter
    p["clip"] = True
    logic.applyClipping(p)
    clip = display.GetClipNode()
    assert display.GetClipping() and clip.GetClippingMethod() == clip.WholeCells
    # by the red slice node through the clipping-node API (not the deprecated red-slice state)
    assert clip.GetClippingNodeState(BreastMesh.RED_SLICE) == clip.ClipNegativeSpace
    assert clip.GetNumberOfClippingNodes() == 1

    # the simulation module takes the mesh with its node sets: fixed chest wall, plates placed
    # against the breast skin and touching the skin between them beyond the chest clearance
    simulation = BreastSimulation.BreastSimulationLogic(scene)
    sp = simulation.getParameterNode()
    sp.set_reference("inputMesh", node)
    simulation.chooseDefaultNodeSets(sp)
    assert (sp["fixedNodeSet"], sp["contactNodeSet"]) == ("chest_wall", "skin")
    sp["compressionPercent"] = 30.0
    simulation.createDefaultMaterials(sp)
    simulation.createCompressionPlates(sp)
    model = simulation.buildModel(sp)
    breast_skin = back.node_set("breast_skin")
    width = np.ptp(back.nodes[breast_skin, 0])
    assert [p.point[0] for p in model.loading.plates] == pytest.approx(
        [back.nodes[breast_skin, 0].min(), back.nodes[breast_skin, 0].max()], abs=1e-3)
    front = back.nodes[np.unique(back.tets[back.cell_data["tissue"] == lt.MUSCLE.label]), 1].min()
    # the plates' flat faces end the plate travel before the chest, rounded back to it: they may
    # touch the breast skin in front of the chest
    contact = model.loading.plates[0].slave_nodes
    assert back.nodes[contact, 1].max() < front and set(contact) <= set(breast_skin)
    for plate in model.loading.plates:
        assert plate.point[1] + plate.edge.distance == pytest.approx(front - 0.15 * width, abs=1e-3)
        assert plate.edge.radius == pytest.approx(0.15 * width, abs=1e-3)

    # a second run with other settings refills the same nodes
    counts = {c: scene.GetNumberOfNodesByClass(c) for c in ("vtkMRMLModelNode", "vtkMRMLTableNode",
                                                             "vtkMRMLPlotChartNode", "vtkMRMLColorTableNode")}
    p["refineInterfaces"] = False
    coarse = logic.run(p)
    assert counts == {c: scene.GetNumberOfNodesByClass(c) for c in counts}
    assert p.reference("outputMesh") is node and node.GetUnstructuredGrid().GetNumberOfCells() == len(coarse.mesh.tets)


def test_settings_reach_the_library(scene, labels):
    logic, p = _set_up(scene, labels)
    p["interfaceEdgeMm"] = 2.0
    p["minDihedralDeg"] = 10.0
    settings = logic.settings(p)
    assert (settings.edge_mm, settings.interface_edge_mm, settings.min_dihedral_deg) == (5.0, 2.0, 10.0)
    p["interfaceEdgeMm"] = 0.0
    assert logic.settings(p).interface_edge_mm is None
    # the exported label map is the one the segmentation was made from (grid and values)
    exported = logic.labelImage(p)
    import SimpleITK as sitk

    np.testing.assert_array_equal(sitk.GetArrayFromImage(exported), sitk.GetArrayFromImage(labels))
    np.testing.assert_allclose(exported.GetOrigin(), labels.GetOrigin(), atol=1e-6)


def test_bad_choices_are_refused_with_the_reason(scene, labels):
    logic = BreastMesh.BreastMeshLogic(scene)
    p = logic.getParameterNode()
    with pytest.raises(ValueError, match="choose the input segmentation"):
        logic.run(p)
    empty = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "Empty")
    p.set_reference("inputSegmentation", empty)
    with pytest.raises(ValueError, match="has no segments"):
        logic.run(p)
    wrong = labels_to_segmentation_node(labels, scene, "Renamed")
    wrong.GetSegmentation().GetSegment("fat").SetName("Segment_1")
    p.set_reference("inputSegmentation", wrong)
    with pytest.raises(ValueError, match=r"segments \['Segment_1'\] are not tissues"):
        logic.run(p)

    logic, p = _set_up(scene, labels)
    for name, value, message in (("edgeMm", 0.0, "element size must be positive"),
                                 ("minRadiusEdge", 1.0, "radius-edge bound must exceed 1"),
                                 ("minDihedralDeg", 25.0, "minimum dihedral angle")):
        p[name] = value
        with pytest.raises(ValueError, match=message):
            logic.run(p)
        p[name] = logic.DEFAULTS[name]
    two = Landmarks(np.array([[0.0, -30.0, 0.0], [5.0, -30.0, 0.0]]), ["a", "b"])
    p.set_reference("nipple", landmarks_to_markups_node(two, scene, "Two"))
    with pytest.raises(ValueError, match="2 points and none is labelled 'nipple'"):
        logic.run(p)
    assert p.reference("outputMesh") is None  # nothing half-made is left behind
