"""Tetrahedral meshes as VTK XML unstructured grid files (``.vtu``), LPS millimetres."""

from __future__ import annotations

from pathlib import Path

import vtk

from BreastBiomechLib.mesh.tetmesh import TetMesh


def _write_xml(path: str | Path, data, writer, what: str, suffix: str) -> Path:
    """Write VTK ``data`` with an XML ``writer`` (binary, compressed) to a ``suffix`` file."""
    path = Path(path)
    if path.suffix != suffix:
        raise ValueError(f"{path}: {what} are written as {suffix} files")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer.SetFileName(str(path))
    writer.SetInputData(data)
    writer.SetDataModeToBinary()
    if not writer.Write():
        raise OSError(f"{path}: VTK could not write the {what}")
    return path


def write_vtu(path: str | Path, mesh: TetMesh) -> Path:
    """Write ``mesh`` with its point and cell arrays; returns the path."""
    return _write_xml(path, mesh.to_vtk(), vtk.vtkXMLUnstructuredGridWriter(), "meshes", ".vtu")


def read_vtu(path: str | Path) -> TetMesh:
    """Read a ``.vtu`` tetrahedral mesh."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    if grid is None or grid.GetNumberOfPoints() == 0:
        raise ValueError(f"{path}: not a readable .vtu mesh, or it has no points")
    return TetMesh.from_vtk(grid)


def write_surface(path: str | Path, surface) -> Path:
    """Write a :class:`~BreastBiomechLib.surface.TriSurface` as a ``.vtp`` polydata file (LPS mm,
    which Slicer assumes for model files); returns the path."""
    return _write_xml(path, surface.to_vtk(), vtk.vtkXMLPolyDataWriter(), "surfaces", ".vtp")
