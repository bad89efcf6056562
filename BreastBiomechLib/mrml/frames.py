"""LPS (ITK, the library) <-> RAS (MRML) conversions of points, vectors and image geometry."""

from __future__ import annotations

import numpy as np
import vtk

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])  # its own inverse


def flip(points: np.ndarray) -> np.ndarray:
    """Points or vectors (..., 3) from LPS to RAS, or back (the map is an involution)."""
    return np.asarray(points, dtype=np.float64) * np.array([-1.0, -1.0, 1.0])


def ijk_to_lps(origin, spacing, direction) -> np.ndarray:
    """4x4 matrix from voxel index (i, j, k) to LPS mm for an ITK image geometry."""
    m = np.eye(4)
    m[:3, :3] = np.asarray(direction, float).reshape(3, 3) @ np.diag(spacing)
    m[:3, 3] = origin
    return m


def to_vtk_matrix(m: np.ndarray) -> vtk.vtkMatrix4x4:
    out = vtk.vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            out.SetElement(i, j, float(m[i, j]))
    return out


def from_vtk_matrix(m: vtk.vtkMatrix4x4) -> np.ndarray:
    return np.array([[m.GetElement(i, j) for j in range(4)] for i in range(4)])


def geometry_from_ijk_to_lps(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin, spacing, direction 3x3) of an index-to-LPS matrix."""
    linear = m[:3, :3]
    spacing = np.linalg.norm(linear, axis=0)
    return m[:3, 3].copy(), spacing, linear / spacing
