"""Results shown over the images: a scalar volume as a coloured overlay with its colour legend,
line segments and surfaces as models coloured by a value, a diverging colour map for signed
values, and subject-hierarchy folders that group a step's nodes.

Geometry arrives in LPS millimetres and is flipped to RAS here, as everywhere in this package.
"""

from __future__ import annotations

import numpy as np
import slicer
import vtk
from vtk.util import numpy_support as nps

from BreastBiomechLib.mrml import frames

DIVERGING_NAME = "BreastBiomech diverging"
MAGNITUDE_COLORS = "vtkMRMLColorTableNodeIron"  # black-red-yellow-white: zero dark, large bright


def diverging_color_node(scene):
    """The scene's blue-white-red colour map for signed values (one per scene, made on first use):
    negative blue, zero white, positive red, over the display node's scalar range."""
    existing = scene.GetFirstNodeByName(DIVERGING_NAME)
    if existing is not None and existing.IsA("vtkMRMLProceduralColorNode"):
        return existing
    node = scene.AddNewNodeByClass("vtkMRMLProceduralColorNode", DIVERGING_NAME)
    function = vtk.vtkColorTransferFunction()
    function.AddRGBPoint(-1.0, 0.23, 0.30, 0.75)
    function.AddRGBPoint(0.0, 0.95, 0.95, 0.95)
    function.AddRGBPoint(1.0, 0.71, 0.02, 0.15)
    node.SetAndObserveColorTransferFunction(function)
    node.SetAttribute("Category", "BreastBiomech")
    return node


def color_legend(displayable, title: str):
    """The displayable node's colour legend (made on first use, as Slicer's Colors module makes
    it: bound to the node's first display node), titled ``title``."""
    display = displayable.GetDisplayNode()
    for i in range(displayable.GetNumberOfDisplayNodes()):
        candidate = displayable.GetNthDisplayNode(i)
        if candidate is not None and candidate.IsA("vtkMRMLColorLegendDisplayNode"):
            candidate.SetTitleText(title)
            return candidate
    scene = displayable.GetScene()
    if not scene.IsNodeClassRegistered("vtkMRMLColorLegendDisplayNode"):  # the Colors module registers it in Slicer
        scene.RegisterNodeClass(slicer.vtkMRMLColorLegendDisplayNode())
    legend = scene.AddNewNodeByClass("vtkMRMLColorLegendDisplayNode", f"{displayable.GetName()} color legend")
    legend.SetTitleText(title)
    legend.SetAndObservePrimaryDisplayNode(display)
    displayable.AddAndObserveDisplayNodeID(legend.GetID())
    legend.Modified()
    return legend


def show_as_overlay(volume_node, color_node_id: str, lower: float, upper: float, title: str,
                    hide_below: float | None = None) -> None:
    """Display a scalar volume node as a coloured overlay: colours ``color_node_id`` over
    [``lower``, ``upper``], values under ``hide_below`` transparent (thresholded), a colour
    legend titled ``title``."""
    display = volume_node.GetDisplayNode()
    if display is None:
        volume_node.CreateDefaultDisplayNodes()
        display = volume_node.GetDisplayNode()
    display.SetAndObserveColorNodeID(color_node_id)
    display.AutoWindowLevelOff()
    display.SetWindowLevelMinMax(float(lower), float(upper))
    if hide_below is not None:
        display.SetApplyThreshold(True)
        display.SetLowerThreshold(float(hide_below))
        display.SetUpperThreshold(1e30)
    color_legend(volume_node, title)


def segments_to_model_node(starts_lps: np.ndarray, ends_lps: np.ndarray, values: np.ndarray, value_name: str,
                           scene, name: str, node=None, color_node_id: str = "vtkMRMLColorTableNodeRainbow"):
    """A model node of line segments from ``starts_lps`` to ``ends_lps`` (K, 3) mm, with the cell
    array ``value_name`` (``values``, K) shown in colour; made, or refilled when ``node`` is given.
    In the slice views the segments are projected onto the slice (a segment meets a slice plane
    in one point at most, which the default intersection display leaves nearly invisible)."""
    starts, ends = np.atleast_2d(np.asarray(starts_lps, float)), np.atleast_2d(np.asarray(ends_lps, float))
    values = np.ravel(np.asarray(values, float))
    if starts.shape != ends.shape or starts.shape[1:] != (3,) or len(values) != len(starts):
        raise ValueError(f"segments need matching (K, 3) starts and ends and K values; got {starts.shape}, "
                         f"{ends.shape}, {values.shape}")
    points, lines = vtk.vtkPoints(), vtk.vtkCellArray()
    for start, end in zip(frames.flip(starts), frames.flip(ends)):
        first = points.InsertNextPoint(*start.tolist())
        points.InsertNextPoint(*end.tolist())
        lines.InsertNextCell(2)
        lines.InsertCellPoint(first)
        lines.InsertCellPoint(first + 1)
    array = nps.numpy_to_vtk(values, deep=True)
    array.SetName(value_name)
    polydata = vtk.vtkPolyData()
    polydata.SetPoints(points)
    polydata.SetLines(lines)
    polydata.GetCellData().AddArray(array)
    node = _model_node(scene, name, node)
    node.SetAndObservePolyData(polydata)
    display = node.GetDisplayNode()
    display.SetActiveScalar(value_name, vtk.vtkAssignAttribute.CELL_DATA)
    display.SetAndObserveColorNodeID(color_node_id)
    display.SetScalarVisibility(True)
    display.SetLineWidth(3.0)
    display.SetVisibility2D(True)
    display.SetSliceDisplayModeToProjection()
    return node


def surface_to_model_node(points_lps: np.ndarray, triangles: np.ndarray, values: np.ndarray, value_name: str,
                          scene, name: str, node=None, color_node_id: str | None = None,
                          symmetric: bool = True):
    """A model node of a triangle surface (points (N, 3) LPS mm, triangles (T, 3) indices) with the
    point array ``value_name`` (``values``, N; NaN where undefined) shown in colour over a range
    symmetric about 0 (``symmetric``) in ``color_node_id`` (default: the diverging map)."""
    points = np.asarray(points_lps, float)
    values = np.ravel(np.asarray(values, float))
    if len(values) != len(points):
        raise ValueError(f"one value per surface point is needed ({len(points)}), not {len(values)}")
    vtk_points = vtk.vtkPoints()
    vtk_points.SetData(nps.numpy_to_vtk(frames.flip(points), deep=True))
    cells = vtk.vtkCellArray()
    triangles = np.asarray(triangles, np.int64)
    connectivity = np.column_stack([np.full(len(triangles), 3), triangles]).ravel()
    cells.SetCells(len(triangles), nps.numpy_to_vtkIdTypeArray(np.ascontiguousarray(connectivity), deep=True))
    array = nps.numpy_to_vtk(values, deep=True)
    array.SetName(value_name)
    polydata = vtk.vtkPolyData()
    polydata.SetPoints(vtk_points)
    polydata.SetPolys(cells)
    polydata.GetPointData().AddArray(array)
    node = _model_node(scene, name, node)
    node.SetAndObservePolyData(polydata)
    display = node.GetDisplayNode()
    display.SetActiveScalar(value_name, vtk.vtkAssignAttribute.POINT_DATA)
    display.SetAndObserveColorNodeID(color_node_id or diverging_color_node(scene).GetID())
    finite = values[np.isfinite(values)]
    reach = float(np.max(np.abs(finite))) if finite.size else 1.0
    display.SetScalarRangeFlag(display.UseManualScalarRange)
    display.SetScalarRange(-reach if symmetric else float(finite.min(initial=0.0)), max(reach, 1e-6))
    display.SetScalarVisibility(True)
    display.SetVisibility2D(True)
    return node


def _model_node(scene, name: str, node=None):
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", name)
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    return node


def folder(scene, name: str, parent: int | None = None) -> int:
    """A subject-hierarchy folder item named ``name`` under ``parent`` (default the scene),
    reused when one of that name is there already; returns its item ID."""
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    parent = hierarchy.GetSceneItemID() if parent is None else parent
    existing = hierarchy.GetItemChildWithName(parent, name)
    if existing:
        return existing
    return hierarchy.CreateFolderItem(parent, name)


def put_in_folder(scene, nodes, folder_item: int) -> None:
    """Move the data nodes ``nodes`` (None entries skipped) under the subject-hierarchy folder."""
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    for node in nodes:
        if node is None:
            continue
        item = hierarchy.GetItemByDataNode(node)
        if item:
            hierarchy.SetItemParent(item, folder_item)
        else:  # Slicer's subject-hierarchy logic adds an item per node; without it (headless) one is made here
            hierarchy.CreateItem(folder_item, node)


def nodes_in_folder(scene, folder_item: int) -> list:
    """The data nodes directly under a subject-hierarchy folder, in their order there."""
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(scene)
    children = vtk.vtkIdList()
    hierarchy.GetItemChildren(folder_item, children)
    nodes = [hierarchy.GetItemDataNode(children.GetId(i)) for i in range(children.GetNumberOfIds())]
    return [node for node in nodes if node is not None]


def remove_with_what_it_owns(scene, node) -> None:
    """Remove ``node`` and the nodes that exist only for it: its display nodes (with a colour
    legend), its storage nodes and, for a plot chart, its plot series. ``scene.RemoveNode`` alone
    leaves them in the scene, where a panel that remakes its results piles them up."""
    owned = []
    for getter, count in (("GetNthDisplayNode", "GetNumberOfDisplayNodes"),
                          ("GetNthStorageNode", "GetNumberOfStorageNodes"),
                          ("GetNthPlotSeriesNode", "GetNumberOfPlotSeriesNodes")):
        if hasattr(node, count):
            owned += [getattr(node, getter)(i) for i in range(getattr(node, count)())]
    scene.RemoveNode(node)
    for other in owned:
        if other is not None and scene.IsNodePresent(other):
            scene.RemoveNode(other)
