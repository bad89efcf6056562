"""A triangulated surface as plain arrays, with its VTK conversion.

Points in millimetres, ITK physical space (LPS); triangles 0-based, counter-clockwise seen from
outside for a closed surface (outward normals)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BreastBiomechLib.mesh.tetmesh import vtk_cells


def corner_angles(p: np.ndarray) -> np.ndarray:
    """Corner angles (..., 3) in degrees of triangles p (..., 3, 3); a corner at an edge of zero
    length (two points in one place) counts as 0."""
    angles = []
    for k in range(3):
        u, v = p[..., (k + 1) % 3, :] - p[..., k, :], p[..., (k + 2) % 3, :] - p[..., k, :]
        lengths = np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1)
        cos = np.divide((u * v).sum(-1), lengths, out=np.ones_like(lengths), where=lengths > 0)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.stack(angles, axis=-1)


@dataclass
class TriSurface:
    """Points (K, 3) LPS mm and triangles (T, 3) int64; ``name`` says what it bounds."""

    points: np.ndarray
    triangles: np.ndarray
    name: str = "surface"

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        if len(self.triangles) and (self.triangles.min() < 0 or self.triangles.max() >= len(self.points)):
            raise ValueError(f"surface {self.name!r}: triangles refer to points outside 0..{len(self.points) - 1}")

    @property
    def area_mm2(self) -> float:
        p = self.points[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())

    @property
    def volume_mm3(self) -> float:
        """Signed enclosed volume (divergence theorem); positive when the normals point outwards."""
        p = self.points[self.triangles]
        return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)

    @property
    def mean_edge_mm(self) -> float:
        p = self.points[self.triangles]
        return float(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).mean()) if len(p) else 0.0

    def flipped(self) -> "TriSurface":
        """The same surface with every triangle's orientation reversed."""
        return TriSurface(self.points, self.triangles[:, ::-1], self.name)

    def to_vtk(self):
        """The surface as vtkPolyData (points in LPS mm)."""
        import vtk
        from vtk.util import numpy_support as nps


        poly = vtk.vtkPolyData()
        points = vtk.vtkPoints()
        points.SetData(nps.numpy_to_vtk(self.points, deep=True))
        poly.SetPoints(points)
        poly.SetPolys(vtk_cells(self.triangles))
        return poly

    @classmethod
    def from_vtk(cls, poly, name: str = "surface") -> "TriSurface":
        """Read the triangles of a vtkPolyData (other cells are refused)."""
        from vtk.util import numpy_support as nps

        if poly.GetNumberOfPoints() == 0 or poly.GetNumberOfPolys() == 0:
            return cls(np.zeros((0, 3)), np.zeros((0, 3), np.int64), name)
        polys = poly.GetPolys()
        offsets = nps.vtk_to_numpy(polys.GetOffsetsArray())
        if np.any(np.diff(offsets) != 3):
            raise ValueError(f"surface {name!r}: only triangles are supported")
        triangles = nps.vtk_to_numpy(polys.GetConnectivityArray()).reshape(-1, 3)
        points = nps.vtk_to_numpy(poly.GetPoints().GetData())
        return cls(points.astype(np.float64), triangles.astype(np.int64), name)
