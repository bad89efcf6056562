"""Round trips between library data (LPS) and real MRML nodes (RAS) in a slicer-core scene."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
import vtk
from vtk.util import numpy_support as nps

from BreastBiomechLib import labels as lt
from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mesh import TetMesh
from images import make_image

slicer = pytest.importorskip("slicer")
mrml = pytest.importorskip("BreastBiomechLib.mrml")

pytestmark = pytest.mark.mrml


def _ras_of_voxel(node, ijk):
    m = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(m)
    return np.array(m.MultiplyPoint([*ijk, 1.0])[:3])


def test_volume_round_trip_keeps_geometry_and_voxels(scene, oblique_geometry):
    rng = np.random.default_rng(0)
    array = rng.normal(size=(6, 7, 9)).astype(np.float32)
    image = make_image(array, oblique_geometry)
    node = mrml.image_to_volume_node(image, scene, "MR")
    # a voxel's physical position: LPS from ITK, RAS from the node, related by the x/y flip
    ijk = (4, 2, 5)
    lps = np.array(image.TransformIndexToPhysicalPoint(ijk))
    np.testing.assert_allclose(_ras_of_voxel(node, ijk), lps * [-1, -1, 1], atol=1e-9)
    back = mrml.image_from_volume_node(node)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), array)
    np.testing.assert_allclose(back.GetOrigin(), image.GetOrigin(), atol=1e-9)
    np.testing.assert_allclose(back.GetSpacing(), image.GetSpacing(), atol=1e-9)
    np.testing.assert_allclose(back.GetDirection(), image.GetDirection(), atol=1e-9)


def test_labelmap_node_and_bad_image(scene, oblique_geometry):
    labels = make_image(np.arange(24, dtype=np.uint8).reshape(2, 3, 4) % 5, oblique_geometry)
    node = mrml.image_to_volume_node(labels, scene, "labels", labelmap=True)
    assert node.IsA("vtkMRMLLabelMapVolumeNode")
    vector = make_image(np.zeros((2, 3, 4, 3), np.float32), oblique_geometry)
    with pytest.raises(ValueError, match="3D scalar image"):
        mrml.image_to_volume_node(vector, scene)


def _phantom_like_labels(geometry) -> sitk.Image:
    z, y, x = np.mgrid[0:12, 0:16, 0:18]
    a = np.zeros((12, 16, 18), np.uint8)
    a[(x - 9) ** 2 + (y - 8) ** 2 + ((z - 6) * 1.5) ** 2 < 40] = lt.FAT.label
    a[(x - 9) ** 2 + (y - 8) ** 2 + ((z - 6) * 1.5) ** 2 < 12] = lt.GLANDULAR.label
    a[y >= 13] = lt.MUSCLE.label
    a[5:7, 6:8, 4:6] = lt.TUMOUR.label
    return make_image(a, geometry)


def test_segmentation_round_trip_names_colours_and_voxels(scene, oblique_geometry):
    labels = _phantom_like_labels(oblique_geometry)
    node = mrml.labels_to_segmentation_node(labels, scene, "Tissues", closed_surface=True)
    segmentation = node.GetSegmentation()
    names = [segmentation.GetNthSegment(i).GetName() for i in range(segmentation.GetNumberOfSegments())]
    assert names == ["fat", "glandular", "muscle", "tumour"]
    for name in names:
        assert segmentation.GetSegment(name).GetColor() == pytest.approx(lt.BY_NAME[name].color)
        surface = node.GetClosedSurfaceInternalRepresentation(name)
        assert surface is not None and surface.GetNumberOfPoints() > 0
    back = mrml.labels_from_segmentation_node(node, scene, reference=labels)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(labels))
    np.testing.assert_allclose(back.GetDirection(), labels.GetDirection(), atol=1e-9)
    np.testing.assert_allclose(back.GetOrigin(), labels.GetOrigin(), atol=1e-9)


def test_segmentation_rejects_unknown_labels_and_segments(scene, oblique_geometry):
    bad = make_image(np.full((2, 2, 2), 9, np.uint8), oblique_geometry)
    with pytest.raises(ValueError, match=r"label values \[9\]"):
        mrml.labels_to_segmentation_node(bad, scene)
    node = mrml.labels_to_segmentation_node(_phantom_like_labels(oblique_geometry), scene)
    node.GetSegmentation().GetSegment("fat").SetName("Segment_1")
    with pytest.raises(ValueError, match="Segment_1"):
        mrml.labels_from_segmentation_node(node, scene)


def _two_tets() -> TetMesh:
    nodes = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 10, 10]], float) + [5.0, -3.0, 2.0]
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    tets[1] = tets[1][[1, 0, 2, 3]] if TetMesh(nodes, tets[1:]).volumes[0] < 0 else tets[1]
    return TetMesh(nodes, tets,
                   point_data={"displacement": np.arange(15, dtype=float).reshape(5, 3), "chest_wall": np.array([1, 0, 0, 1, 0], np.uint8)},
                   cell_data={"tissue": np.array([1, 4], np.uint8), "fraction_glandular": np.array([0.25, 0.5])})


def test_tetmesh_model_node_round_trip(scene):
    mesh = _two_tets()
    node = mrml.tetmesh_to_model_node(mesh, scene, "Mesh")
    grid = node.GetUnstructuredGrid()
    assert grid.GetNumberOfCells() == 2
    np.testing.assert_allclose(grid.GetPoint(1), mesh.nodes[1] * [-1, -1, 1])
    back = mrml.tetmesh_from_model_node(node)
    np.testing.assert_allclose(back.nodes, mesh.nodes)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    assert np.all(back.volumes > 0)
    for key in mesh.point_data:
        np.testing.assert_array_equal(back.point_data[key], mesh.point_data[key])
    for key in mesh.cell_data:
        np.testing.assert_array_equal(back.cell_data[key], mesh.cell_data[key])
    # the displacement array is a vector: flipped with the points in the scene
    u_ras = nps.vtk_to_numpy(grid.GetPointData().GetArray("displacement"))
    np.testing.assert_allclose(u_ras, mesh.point_data["displacement"] * [-1, -1, 1])


def test_model_node_without_volume_mesh_is_refused(scene):
    node = scene.AddNewNodeByClass("vtkMRMLModelNode", "surface")
    with pytest.raises(ValueError, match="unstructured grid"):
        mrml.tetmesh_from_model_node(node)


def _landmarks() -> Landmarks:
    return Landmarks(np.array([[1.5, -2.0, 30.25], [-40.0, 12.0, -3.5], [0.0, -95.0, 1.0]]),
                     ["L01", "F1", "nipple"], ["duct branching", "skin fiducial, medial", "nipple tip"])


def test_markups_node_round_trip(scene):
    landmarks = _landmarks()
    node = mrml.landmarks_to_markups_node(landmarks, scene)
    assert node.GetNumberOfControlPoints() == 3
    ras = [0.0, 0.0, 0.0]
    node.GetNthControlPointPosition(2, ras)
    np.testing.assert_allclose(ras, landmarks.positions[2] * [-1, -1, 1])
    back = mrml.landmarks_from_markups_node(node)
    np.testing.assert_allclose(back.positions, landmarks.positions)
    assert back.labels == landmarks.labels and back.descriptions == landmarks.descriptions


def test_mrk_json_file_is_read_by_slicers_own_reader(scene, tmp_path):
    landmarks = _landmarks()
    path = write_markups(tmp_path / "landmarks.mrk.json", landmarks)
    storage = scene.AddNode(slicer.vtkMRMLMarkupsJsonStorageNode())
    storage.SetFileName(str(path))
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode")
    assert storage.ReadData(node)
    back = mrml.landmarks_from_markups_node(node)
    np.testing.assert_allclose(back.positions, landmarks.positions, atol=1e-9)
    assert back.labels == landmarks.labels
    # and a file written by Slicer's writer (RAS or LPS, its choice) reads back with our reader
    out = tmp_path / "slicer.mrk.json"
    storage.SetFileName(str(out))
    assert storage.WriteData(node)
    assert json.loads(out.read_text())["markups"][0]["type"] == "Fiducial"
    np.testing.assert_allclose(read_markups(out).positions, landmarks.positions, atol=1e-6)


def test_grid_transform_round_trip_and_point_mapping(scene, oblique_geometry):
    z, y, x = np.mgrid[0:5, 0:6, 0:7].astype(float)
    u = np.stack([0.3 * x + 0.1 * z, -0.2 * y, 0.05 * x * y], axis=-1)  # LPS mm, smooth
    field = make_image(u, oblique_geometry)
    node = mrml.displacement_field_to_grid_transform_node(field, scene)
    # a grid point p (LPS) goes to p + u(p): check through the node's own to-parent transform
    ijk = (3, 2, 1)
    p = np.array(field.TransformIndexToPhysicalPoint(ijk))
    moved_ras = np.array(node.GetTransformToParent().TransformPoint(*(p * [-1, -1, 1])))
    np.testing.assert_allclose(moved_ras * [-1, -1, 1], p + u[ijk[2], ijk[1], ijk[0]], atol=1e-6)
    back = mrml.displacement_field_from_grid_transform_node(node)
    np.testing.assert_allclose(sitk.GetArrayFromImage(back), u, atol=1e-12)
    np.testing.assert_allclose(back.GetOrigin(), field.GetOrigin(), atol=1e-9)
    np.testing.assert_allclose(back.GetSpacing(), field.GetSpacing(), atol=1e-9)
    np.testing.assert_allclose(back.GetDirection(), field.GetDirection(), atol=1e-9)


def test_parameter_node_typed_values_and_references(scene, oblique_geometry):
    defaults = {"seed": 1, "volume_cm3": 800.0, "tumour": True, "case": "custom"}
    params = mrml.ParameterNode(scene, "BreastBiomech", defaults, roles=("volume",))
    assert params["volume_cm3"] == 800.0 and params["tumour"] is True
    params["seed"] = 7
    params["tumour"] = False
    volume = mrml.image_to_volume_node(make_image(np.zeros((2, 2, 2), np.float32), oblique_geometry), scene)
    params.set_reference("volume", volume)
    again = mrml.ParameterNode(scene, "BreastBiomech", defaults, roles=("volume",))
    assert again.node is params.node
    assert again["seed"] == 7 and again["tumour"] is False and again.reference("volume") is volume
    # as Slicer's ScriptedLoadableModuleLogic and parameterNodeWrapper store them: the module's
    # name in the "ModuleName" attribute (restored after a scene close drops it), booleans "True"/"False"
    assert params.node.GetAttribute("ModuleName") == "BreastBiomech"
    assert params.node.GetParameter("tumour") == "False"
    params.node.RemoveAttribute("ModuleName")
    assert mrml.ParameterNode(scene, "BreastBiomech", defaults).node.GetAttribute("ModuleName") == "BreastBiomech"
    params.node.SetParameter("tumour", "true")  # what earlier versions wrote is still read
    assert params["tumour"] is True
    with pytest.raises(KeyError, match="unknown parameter"):
        again["nope"]
    with pytest.raises(ValueError):
        again["seed"] = "seven"
    planes = [scene.AddNewNodeByClass("vtkMRMLMarkupsPlaneNode", f"plate{i}") for i in range(3)]
    multi = mrml.ParameterNode(scene, "Multi", {}, roles=("plates",))
    multi.set_references("plates", planes)
    assert multi.references("plates") == planes
    multi.set_references("plates", planes[1:])
    assert multi.references("plates") == planes[1:]


def test_materials_table_round_trip_in_ras(scene):
    from BreastBiomechLib.solver.materials import Material, fibre_direction

    fibre = tuple(float(c) for c in fibre_direction(np.radians(60.0), np.radians(30.0)))
    materials = {lt.FAT.label: Material(10e3, 0.49),
                 lt.TUMOUR.label: Material(120e3, 0.495, eta=4e3, fibre=fibre, density=1050.0, prony=((0.4, 0.2),))}
    node = mrml.materials_to_table_node(materials, scene)
    assert node.GetCellText(1, 0) == "tumour"
    ras = [node.GetTable().GetColumnByName(c).GetValue(1) for c in ("fibre R", "fibre A", "fibre S")]
    np.testing.assert_allclose(ras, np.array(fibre) * [-1, -1, 1])
    assert mrml.materials_from_table_node(node) == materials
    # a table read from a CSV file holds text columns
    text = vtk.vtkStringArray()
    text.SetName("E (Pa)")
    for value in ("12e3", "abc"):
        text.InsertNextValue(value)
    node.GetTable().RemoveColumnByName("E (Pa)")
    node.GetTable().AddColumn(text)
    with pytest.raises(ValueError, match="tumour: E \\(Pa\\) is 'abc', not a number"):
        mrml.materials_from_table_node(node)
    text.SetValue(1, "120000")
    assert mrml.materials_from_table_node(node)[lt.FAT.label].E == 12e3
    node.GetTable().GetColumnByName("fibre S").SetValue(0, 0.0)
    node.GetTable().GetColumnByName("fibre R").SetValue(0, 0.0)
    with pytest.raises(ValueError, match="fat: the fibre direction must not be zero"):
        mrml.materials_from_table_node(node)
    with pytest.raises(ValueError, match="Prony term"):
        mrml.materials_to_table_node({1: Material(1e3, 0.4, prony=((0.1, 1.0), (0.1, 2.0)))}, scene)


def test_plate_plane_node_round_trip(scene):
    from BreastBiomechLib.solver.model import Plate

    plate = Plate([10.0, -20.0, 5.0], [0.6, 0.8, 0.0], [3.0, 4.0, 0.0], [1, 2, 3], "paddle")
    node = mrml.plate_to_plane_node(plate, scene)
    origin = [0.0, 0.0, 0.0]
    node.GetOriginWorld(origin)
    np.testing.assert_allclose(origin, [-10.0, 20.0, 5.0])
    back = mrml.plate_from_plane_node(node, plate.slave_nodes)
    np.testing.assert_allclose(back.point, plate.point, atol=1e-9)
    np.testing.assert_allclose(back.normal, plate.normal, atol=1e-9)
    np.testing.assert_allclose(back.displacement, plate.displacement, atol=1e-9)
    flipped = mrml.plate_from_plane_node(node, plate.slave_nodes, towards=plate.point - 50.0 * plate.normal)
    np.testing.assert_allclose(flipped.normal, -plate.normal, atol=1e-9)
    np.testing.assert_allclose(flipped.displacement, -plate.displacement, atol=1e-9)
    node.SetAttribute("BreastBiomech.PlateTravelMm", "five")
    with pytest.raises(ValueError, match="'paddle': its travel 'five' is not a number"):
        mrml.plate_from_plane_node(node, plate.slave_nodes)
    with pytest.raises(ValueError, match="markups plane"):
        mrml.plate_from_plane_node(scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode"), [])


def test_a_side_by_side_comparison_shows_both_views_in_one_plane_linked(scene):
    """Slicer keeps an existing Yellow view sagittal when the side-by-side layout is chosen; the
    comparison sets it to Red's plane, links the two and puts each view's volumes in."""
    from BreastBiomechLib.mrml.views import compare_side_by_side

    slicer = pytest.importorskip("slicer")
    slicer.vtkMRMLSliceNode.AddDefaultSliceOrientationPresets(scene)  # what the application's slice logic adds
    views = []
    for name, orientation in (("Red", "Axial"), ("Yellow", "Sagittal")):
        slice_node = scene.AddNewNodeByClass("vtkMRMLSliceNode")
        slice_node.SetLayoutName(name)
        assert slice_node.SetOrientation(orientation)
        composite = scene.AddNewNodeByClass("vtkMRMLSliceCompositeNode")
        composite.SetLayoutName(name)
        views.append((slice_node, composite))
    volumes = [scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode").GetID() for _ in range(3)]
    assert compare_side_by_side(views, volumes[0], volumes[1:]) == "Axial"
    for (slice_node, composite), foreground in zip(views, volumes[1:]):
        assert slice_node.GetOrientationString() == "Axial" and composite.GetLinkedControl()
        assert composite.GetBackgroundVolumeID() == volumes[0] and composite.GetForegroundVolumeID() == foreground
    with pytest.raises(ValueError, match="2 views for 1"):
        compare_side_by_side(views, volumes[0], volumes[1:2])


def test_a_removed_result_takes_what_it_owns_with_it(scene):
    """A panel that remakes its results removes the old nodes: their display, colour-legend and
    storage nodes and a chart's plot series go with them (scene.RemoveNode alone leaves them)."""
    from BreastBiomechLib.mrml import columns_to_table_node, plot_chart_node
    from BreastBiomechLib.mrml.overlays import remove_with_what_it_owns, show_as_overlay

    before = scene.GetNumberOfNodes()
    volume = scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "overlay")
    image = vtk.vtkImageData()
    image.SetDimensions(3, 3, 3)
    image.AllocateScalars(vtk.VTK_FLOAT, 1)
    volume.SetAndObserveImageData(image)
    show_as_overlay(volume, "vtkMRMLColorTableNodeIron", 0.0, 1.0, "|r| (mm)")
    table = columns_to_table_node({"x": np.arange(3.0), "y": np.arange(3.0)}, scene, "table")
    chart = plot_chart_node(table, "x", ["y"], scene, "chart", "y")
    assert scene.GetNumberOfNodes() - before == 6  # volume, display, legend, table, chart, series
    for node in (volume, chart, table):
        remove_with_what_it_owns(scene, node)
    assert scene.GetNumberOfNodes() == before
