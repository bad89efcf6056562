"""Displacement fields (SimpleITK vector images, LPS) <-> MRML grid transform nodes (RAS).

A displacement field ``u`` on a grid maps a point ``x`` to ``x + u(x)`` (LPS mm). In the node it
becomes the transform *to parent*, so a model or markups node placed under it moves as the field
says (for resampling a volume Slicer inverts it as needed).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import slicer
import vtk
from vtk.util import numpy_support as nps

from BreastBiomechLib.mrml import frames


def displacement_field_to_grid_transform_node(field: sitk.Image, scene, name: str = "Displacement", node=None):
    """Make (or refill) a grid transform node from a 3-component displacement field image."""
    if field.GetDimension() != 3 or field.GetNumberOfComponentsPerPixel() != 3:
        raise ValueError("a displacement field is a 3D image with 3 components per voxel (LPS mm)")
    u_lps = sitk.GetArrayFromImage(field).astype(np.float64)  # z, y, x, 3
    nz, ny, nx, _ = u_lps.shape
    grid = vtk.vtkImageData()
    grid.SetDimensions(nx, ny, nz)
    origin_ras = frames.flip(np.array(field.GetOrigin()))
    grid.SetOrigin(*origin_ras)
    grid.SetSpacing(*field.GetSpacing())
    grid.GetPointData().SetScalars(nps.numpy_to_vtk(frames.flip(u_lps).reshape(-1, 3), deep=True))
    direction_ras = frames.LPS_TO_RAS @ np.array(field.GetDirection()).reshape(3, 3)
    matrix = np.eye(4)
    matrix[:3, :3] = direction_ras
    transform = slicer.vtkOrientedGridTransform()
    transform.SetDisplacementGridData(grid)
    transform.SetGridDirectionMatrix(frames.to_vtk_matrix(matrix))
    transform.SetInterpolationModeToLinear()
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLGridTransformNode", name)
    node.SetAndObserveTransformToParent(transform)
    return node


def displacement_field_from_grid_transform_node(node) -> sitk.Image:
    """The node's to-parent displacement grid as a SimpleITK vector image in LPS."""
    transform = node.GetTransformToParentAs("vtkOrientedGridTransform", False, True) if node else None
    if transform is None or transform.GetDisplacementGrid() is None:
        raise ValueError("the transform node holds no to-parent displacement grid")
    grid = transform.GetDisplacementGrid()
    nx, ny, nz = grid.GetDimensions()
    u_ras = nps.vtk_to_numpy(grid.GetPointData().GetScalars()).astype(np.float64).reshape(nz, ny, nx, 3)
    u_ras = u_ras * transform.GetDisplacementScale() + transform.GetDisplacementShift()
    field = sitk.GetImageFromArray(frames.flip(u_ras), isVector=True)
    field.SetOrigin(tuple(frames.flip(np.array(grid.GetOrigin()))))
    field.SetSpacing(grid.GetSpacing())
    direction_ras = frames.from_vtk_matrix(transform.GetGridDirectionMatrix())[:3, :3]
    field.SetDirection(tuple((frames.LPS_TO_RAS @ direction_ras).ravel()))
    return field

