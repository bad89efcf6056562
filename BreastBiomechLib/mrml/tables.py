"""Per-tissue material tables and solver histories <-> MRML table nodes, and plot charts of them.

Fibre directions are shown in RAS (as everything in Slicer) and held in LPS by the library.
Moduli in Pa, density kg/m^3, Prony time constants s, energies J, forces N, time s.
"""

from __future__ import annotations

import numpy as np
import vtk

from BreastBiomechLib import labels
from BreastBiomechLib.mrml import frames
from BreastBiomechLib.solver.materials import Material

MATERIAL_COLUMNS = ("tissue", "E (Pa)", "nu", "eta (Pa)", "fibre R", "fibre A", "fibre S", "density (kg/m3)",
                    "prony g1", "prony tau1 (s)")


def materials_to_table_node(materials: dict[int, Material], scene, name: str = "Materials", node=None):
    """One row per tissue label (by name), the columns of ``MATERIAL_COLUMNS``; one Prony term."""
    if any(len(m.prony) > 1 for m in materials.values()):
        raise ValueError("the materials table holds one Prony term per tissue; use a case file for more")
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLTableNode", name)
    table = vtk.vtkTable()
    names = vtk.vtkStringArray()
    names.SetName(MATERIAL_COLUMNS[0])
    table.AddColumn(names)
    for column in MATERIAL_COLUMNS[1:]:
        array = vtk.vtkDoubleArray()
        array.SetName(column)
        table.AddColumn(array)
    for label in sorted(materials):
        m = materials[label]
        g, tau = m.prony[0] if m.prony else (0.0, 1.0)
        values = [m.E, m.nu, m.eta, *(frames.flip(m.fibre) + 0.0).tolist(), m.density, g, tau]  # + 0.0: no -0
        table.InsertNextBlankRow()
        row = table.GetNumberOfRows() - 1
        table.SetValue(row, 0, vtk.vtkVariant(labels.tissue(label).name))
        for column, value in enumerate(values, start=1):
            table.SetValue(row, column, vtk.vtkVariant(float(value)))
    node.SetAndObserveTable(table)
    node.SetUseColumnTitleAsColumnHeader(True)
    return node


def materials_from_table_node(node) -> dict[int, Material]:
    """{tissue label: Material} from a materials table (as made by materials_to_table_node and
    edited by the user); every bad cell is reported with its row and column."""
    if node is None or node.GetTable() is None:
        raise ValueError("choose a materials table (the module's 'Default materials' button makes one)")
    table = node.GetTable()
    missing = [c for c in MATERIAL_COLUMNS if table.GetColumnByName(c) is None]
    if missing:
        raise ValueError(f"materials table {node.GetName()!r} lacks the columns {missing}")
    materials = {}
    for row in range(table.GetNumberOfRows()):
        name = table.GetColumnByName("tissue").GetValue(row).strip()
        try:
            tissue = labels.tissue(int(name) if name.isdigit() else name)
        except KeyError as error:
            raise ValueError(f"materials table row {row + 1}: {error.args[0]}") from None
        if tissue.label in materials:
            raise ValueError(f"materials table row {row + 1}: tissue {tissue.name!r} is listed twice")

        def number(column: str) -> float:
            variant = table.GetColumnByName(column).GetVariantValue(row)
            text = variant.ToString()  # a table read from a file may hold text
            try:
                value = variant.ToDouble() if variant.IsNumeric() else float(text)
            except ValueError:
                raise ValueError(f"materials table, {tissue.name}: {column} is {text!r}, not a number") from None
            if not np.isfinite(value):
                raise ValueError(f"materials table, {tissue.name}: {column} must be finite")
            return value

        fibre = frames.flip([number("fibre R"), number("fibre A"), number("fibre S")])
        norm = np.linalg.norm(fibre)
        if norm == 0:
            raise ValueError(f"materials table, {tissue.name}: the fibre direction must not be zero")
        g = number("prony g1")
        try:
            materials[tissue.label] = Material(
                E=number("E (Pa)"), nu=number("nu"), eta=number("eta (Pa)"), fibre=tuple(float(c) for c in fibre / norm),
                density=number("density (kg/m3)"), prony=((g, number("prony tau1 (s)")),) if g > 0 else ())
        except ValueError as error:
            raise ValueError(f"materials table, {tissue.name}: {error}") from None
    if not materials:
        raise ValueError(f"materials table {node.GetName()!r} has no rows")
    return materials


def columns_to_table_node(columns: dict[str, np.ndarray], scene, name: str, node=None):
    """A table node with one column per entry (all of the same length): numbers become double
    columns, text (str values) string columns, e.g. a history or a report."""
    lengths = {len(np.ravel(values)) for values in columns.values()}
    if len(lengths) > 1:
        raise ValueError(f"table columns differ in length: {sorted(lengths)}")
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLTableNode", name)
    table = vtk.vtkTable()
    for column, values in columns.items():
        values = np.ravel(values)
        text = values.dtype.kind in "USO"
        array = vtk.vtkStringArray() if text else vtk.vtkDoubleArray()
        array.SetName(column)
        for value in values if text else values.astype(float):
            array.InsertNextValue(str(value) if text else value)
        table.AddColumn(array)
    node.SetAndObserveTable(table)
    node.SetUseColumnTitleAsColumnHeader(True)
    return node


def plot_chart_node(table_node, x_column: str, y_columns: list[str], scene, title: str, y_title: str,
                    node=None, bars: bool = False):
    """A line chart (``bars``: a bar chart, e.g. a histogram) of ``y_columns`` against
    ``x_column`` of a table node (series reused by name)."""
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLPlotChartNode", title)
    node.SetTitle(title)
    node.SetXAxisTitle(x_column)
    node.SetYAxisTitle(y_title)
    existing = {node.GetNthPlotSeriesNode(i).GetName(): node.GetNthPlotSeriesNode(i)
                for i in range(node.GetNumberOfPlotSeriesNodes())}
    node.RemoveAllPlotSeriesNodeIDs()
    for index, column in enumerate(y_columns):
        if table_node.GetTable().GetColumnByName(column) is None:
            raise ValueError(f"table {table_node.GetName()!r} has no column {column!r}")
        series = existing.get(f"{title}: {column}") or scene.AddNewNodeByClass("vtkMRMLPlotSeriesNode",
                                                                                f"{title}: {column}")
        series.SetAndObserveTableNodeID(table_node.GetID())
        series.SetXColumnName(x_column)
        series.SetYColumnName(column)
        series.SetPlotType(series.PlotTypeBar if bars else series.PlotTypeScatter)
        series.SetMarkerStyle(series.MarkerStyleNone)
        series.SetColor(*_SERIES_COLOURS[index % len(_SERIES_COLOURS)])
        node.AddAndObservePlotSeriesNodeID(series.GetID())
    return node


_SERIES_COLOURS = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
                   (0.58, 0.40, 0.74), (0.55, 0.34, 0.29))
