"""Tetrahedral meshing of the whole model with TetGen, refined by points of the tissue surfaces
(the seed's section 2.2.3): the outer (body) surface is the boundary; sparse points of each
internal tissue surface are inserted as extra vertices, so element faces follow the tissue
interfaces without a multi-domain mesher.

Geometry in LPS mm."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from BreastBiomechLib.mesh.tetmesh import TetMesh, regular_tet_volume_mm3
from BreastBiomechLib.solver.memory import check_meshing_fits
from BreastBiomechLib.surface.checks import check_surface
from BreastBiomechLib.surface.trisurface import TriSurface


@dataclass
class TetGenSettings:
    """Element size and quality. ``edge_mm``: interior element size (the volume bound is that of
    a regular tet of this edge); ``interface_edge_mm``: spacing of the points inserted on tissue
    interfaces (None: ``edge_mm``); ``min_radius_edge`` and ``min_dihedral_deg``: TetGen's
    quality bounds (-q); ``boundary_clearance``: interface points closer to the outer surface
    than this fraction of the interface spacing are not inserted (they would make slivers)."""

    edge_mm: float = 3.0
    interface_edge_mm: float | None = None
    min_radius_edge: float = 1.5
    min_dihedral_deg: float = 12.0
    boundary_clearance: float = 0.5

    def __post_init__(self) -> None:
        if self.edge_mm <= 0 or (self.interface_edge_mm is not None and self.interface_edge_mm <= 0):
            raise ValueError("element edge lengths must be positive (mm)")
        if self.min_radius_edge < 1.1:
            raise ValueError("TetGen needs a radius-edge bound of at least 1.1 (1.5 is a good default)")
        if not 0 <= self.min_dihedral_deg <= 18:
            raise ValueError("the minimum dihedral angle must lie in 0-18 degrees (TetGen may not terminate above)")

    @property
    def interface_spacing_mm(self) -> float:
        return self.edge_mm if self.interface_edge_mm is None else self.interface_edge_mm


def interface_points(boundary: TriSurface, interfaces: list[TriSurface], spacing_mm: float,
                     clearance_mm: float) -> np.ndarray:
    """Points (K, 3) mm of the internal tissue surfaces to insert: inside the boundary surface by
    at least ``clearance_mm``, and no two closer than 0.6 ``spacing_mm`` (greedy thinning, so
    neighbouring interfaces do not make short edges)."""
    import vtk
    from vtk.util import numpy_support as nps

    points = [s.points for s in interfaces if s is not None and len(s.points)]
    if not points:
        return np.zeros((0, 3))
    points = np.concatenate(points)
    distance = vtk.vtkImplicitPolyDataDistance()
    distance.SetInput(boundary.to_vtk())
    signed = np.empty(len(points))
    values = vtk.vtkDoubleArray()
    distance.FunctionValue(nps.numpy_to_vtk(points, deep=True), values)
    signed[:] = nps.vtk_to_numpy(values)
    points = points[signed < -clearance_mm]  # negative inside
    if len(points) == 0:
        return points
    tree = cKDTree(points)
    neighbours = tree.query_ball_point(points, 0.6 * spacing_mm)
    keep = np.ones(len(points), bool)
    for i, near in enumerate(neighbours):
        if keep[i]:
            keep[[j for j in near if j > i]] = False
    return points[keep]


@contextmanager
def _in_scratch_folder():
    """Run the block with a temporary working folder (removed afterwards)."""
    previous = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="breastbiomech-tetgen-") as folder:
        os.chdir(folder)
        try:
            yield
        finally:
            os.chdir(previous)


def tetrahedralize(boundary: TriSurface, extra_points: np.ndarray, settings: TetGenSettings,
                   memory_limit_bytes: int | None = None) -> TetMesh:
    """TetGen quality mesh of the region inside ``boundary`` (a closed, oriented 2-manifold)
    with ``extra_points`` (K, 3) mm inside it as vertices. Tets positively oriented. Clear
    errors for a defective surface, a mesh too fine for the host's available memory (or
    ``memory_limit_bytes``; :class:`~BreastBiomechLib.solver.memory.TooLargeForMemory`, before
    TetGen starts) or a TetGen failure."""
    import tetgen


    problems = check_surface(boundary).problems()
    if problems:
        raise ValueError(f"the {boundary.name} surface cannot be meshed: {'; '.join(problems)}. "
                         "Smooth the label map more (blur_mm) or fill its holes.")
    check_meshing_fits(abs(boundary.volume_mm3), settings.edge_mm, f"the {boundary.name} surface", memory_limit_bytes)
    points = np.concatenate([boundary.points, np.asarray(extra_points, float).reshape(-1, 3)])
    generator = tetgen.TetGen(points, boundary.triangles.astype(np.int32))
    max_volume = regular_tet_volume_mm3(settings.edge_mm)
    try:
        with _in_scratch_folder():  # TetGen writes _skipped.* files where it fails: not in the user's folder
            nodes, tets, *_ = generator.tetrahedralize(quality=True, minratio=settings.min_radius_edge,
                                                       mindihedral=settings.min_dihedral_deg, maxvolume=max_volume,
                                                       optmaxdihedral=165.0, nobisect=True)
    except RuntimeError as error:
        raise RuntimeError(f"TetGen could not mesh the {boundary.name} surface ({error}); the surface may "
                           "intersect itself where the tissue is thinner than the edge length: use a smaller "
                           "edge_mm or a larger blur_mm") from None
    if len(tets) == 0:
        raise RuntimeError(f"TetGen returned no elements for the {boundary.name} surface")
    mesh = TetMesh(nodes, tets)
    negative = mesh.volumes < 0
    if negative.any():
        fixed = mesh.tets.copy()
        fixed[negative] = fixed[negative][:, [0, 2, 1, 3]]
        mesh = TetMesh(nodes, fixed)
    used = np.zeros(len(mesh.nodes), bool)
    used[mesh.tets.ravel()] = True
    if not used.all():  # points TetGen left out of every element (outside or merged)
        remap = np.cumsum(used) - 1
        mesh = TetMesh(mesh.nodes[used], remap[mesh.tets])
    return mesh
