"""Tetrahedral meshes as VTK XML unstructured grid files (``.vtu``), LPS millimetres."""

from __future__ import annotations

from pathlib import Path

import vtk

from BreastBiomechLib.mesh.tetmesh import TetMesh


def write_vtu(path: str | Path, mesh: TetMesh) -> Path:
    """Write ``mesh`` with its point and cell arrays (binary, compressed); returns the path."""
    path = Path(path)
    if path.suffix != ".vtu":
        raise ValueError(f"{path}: meshes are written as .vtu files")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = vtk.vtkXMLUnstructuredGridWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(mesh.to_vtk())
    writer.SetDataModeToBinary()
    if not writer.Write():
        raise OSError(f"{path}: VTK could not write the mesh")
    return path


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
    path = Path(path)
    if path.suffix != ".vtp":
        raise ValueError(f"{path}: surfaces are written as .vtp files")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(surface.to_vtk())
    writer.SetDataModeToBinary()
    if not writer.Write():
        raise OSError(f"{path}: VTK could not write the surface")
    return path
