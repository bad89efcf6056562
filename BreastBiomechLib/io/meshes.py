"""Tetrahedral meshes as VTK XML unstructured grid files (``.vtu``), LPS millimetres."""

from __future__ import annotations

from pathlib import Path

import vtk

from BreastBiomechLib.errors import InputError, reading
from BreastBiomechLib.io.atomic import atomic_path
from BreastBiomechLib.mesh.tetmesh import TetMesh, check_mesh


def _write_xml(path: str | Path, data, writer, what: str, suffix: str) -> Path:
    """Write VTK ``data`` with an XML ``writer`` (binary, compressed) to a ``suffix`` file."""
    path = Path(path)
    if path.suffix != suffix:
        raise ValueError(f"{path}: {what} are written as {suffix} files")
    with atomic_path(path) as temporary:
        writer.SetFileName(str(temporary))
        writer.SetInputData(data)
        writer.SetDataModeToBinary()
        if not writer.Write():
            raise OSError(f"{path}: VTK could not write the {what}")
    return path


def write_vtu(path: str | Path, mesh: TetMesh) -> Path:
    """Write ``mesh`` with its point and cell arrays; returns the path."""
    return _write_xml(path, mesh.to_vtk(), vtk.vtkXMLUnstructuredGridWriter(), "meshes", ".vtu")


def read_vtu(path: str | Path) -> TetMesh:
    """Read a ``.vtu`` tetrahedral mesh to simulate: linear tetrahedra only, finite coordinates,
    every element positively oriented with a volume, no element twice, every node in an element.
    Anything else raises :class:`~BreastBiomechLib.errors.InputError` naming what and where."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    remedy = "write it again from the mesher (`breastbiomech mesh`), as linear tetrahedra in LPS mm"
    with reading(path, ".vtu tetrahedral mesh", remedy):
        reader = vtk.vtkXMLUnstructuredGridReader()
        errors = []
        reader.AddObserver("ErrorEvent", lambda caller, event: errors.append(event))
        shown = vtk.vtkObject.GetGlobalWarningDisplay()
        vtk.vtkObject.GlobalWarningDisplayOff()  # VTK's own messages would print, not raise
        try:
            reader.SetFileName(str(path))
            reader.Update()
        finally:
            vtk.vtkObject.SetGlobalWarningDisplay(shown)
        grid = reader.GetOutput()
        if errors or grid is None or grid.GetNumberOfPoints() == 0:
            raise InputError(f"{path}: not a readable .vtu mesh, or it has no points; {remedy}")
        mesh = TetMesh.from_vtk(grid)
        check_mesh(mesh, str(path))
    return mesh


def write_surface(path: str | Path, surface) -> Path:
    """Write a :class:`~BreastBiomechLib.surface.TriSurface` as a ``.vtp`` polydata file (LPS mm,
    which Slicer assumes for model files); returns the path."""
    return _write_xml(path, surface.to_vtk(), vtk.vtkXMLPolyDataWriter(), "surfaces", ".vtp")
