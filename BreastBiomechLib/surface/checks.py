"""Topology checks of a triangulated surface: closed (watertight), manifold (edges and vertices),
consistently oriented, normals outwards. Checked from the triangles, not assumed from the
algorithm that made them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from BreastBiomechLib.rows import unique_rows
from BreastBiomechLib.surface.trisurface import TriSurface


@dataclass
class SurfaceCheck:
    """Counts of topology defects; ``ok`` when there are none and the surface encloses a positive
    volume with outward normals."""

    name: str
    triangles: int
    boundary_edges: int        # edges of one triangle: holes
    nonmanifold_edges: int     # edges of three or more triangles
    nonmanifold_vertices: int  # vertices whose triangles form more than one fan (bow ties)
    misoriented_edges: int     # edges walked the same way by both triangles (inconsistent orientation)
    components: int            # connected pieces
    volume_mm3: float          # signed enclosed volume

    @property
    def ok(self) -> bool:
        return not self.problems()

    def problems(self) -> list[str]:
        """Each defect in words (empty when the surface is a closed, oriented 2-manifold)."""
        found = []
        if self.triangles == 0:
            return [f"surface {self.name!r} is empty"]
        if self.boundary_edges:
            found.append(f"{self.boundary_edges} boundary edges (holes)")
        if self.nonmanifold_edges:
            found.append(f"{self.nonmanifold_edges} non-manifold edges")
        if self.nonmanifold_vertices:
            found.append(f"{self.nonmanifold_vertices} non-manifold vertices")
        if self.misoriented_edges:
            found.append(f"{self.misoriented_edges} edges with inconsistent triangle orientation")
        if not found and self.volume_mm3 <= 0:
            found.append("normals point inwards (negative enclosed volume)")
        return found


def check_surface(surface: TriSurface) -> SurfaceCheck:
    """Topology of ``surface`` (see :class:`SurfaceCheck`)."""
    tri = surface.triangles
    if len(tri) == 0:
        return SurfaceCheck(surface.name, 0, 0, 0, 0, 0, 0, 0.0)
    directed = np.stack([tri, np.roll(tri, -1, axis=1)], axis=2).reshape(-1, 2)  # (3T, 2): a->b
    undirected = np.sort(directed, axis=1)
    edges, edge_of, counts = unique_rows(undirected, return_inverse=True, return_counts=True)
    _, directed_counts = unique_rows(directed, return_counts=True)
    misoriented = int(np.count_nonzero(directed_counts > 1))

    # vertex fans: the corners of the triangles around a vertex are linked when their triangles
    # share an edge through that vertex; a manifold vertex has one linked group
    n_tri = len(tri)
    half_tri = np.repeat(np.arange(n_tri), 3)
    pairs = counts[edge_of] == 2
    order = np.argsort(edge_of[pairs], kind="stable")
    first, second = half_tri[pairs][order][0::2], half_tri[pairs][order][1::2]
    shared = edges[edge_of[pairs][order][0::2]]
    links = [(_corner_id(tri, first, shared[:, c]), _corner_id(tri, second, shared[:, c])) for c in (0, 1)]
    rows = np.concatenate([a for a, _ in links])
    cols = np.concatenate([b for _, b in links])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_tri, 3 * n_tri))
    _, group = connected_components(graph, directed=False)
    vertex = tri.ravel()
    fans = unique_rows(np.stack([vertex, group], axis=1))[:, 0]
    nonmanifold_vertices = int(np.count_nonzero(np.bincount(fans) > 1))

    tri_graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(n_tri, n_tri))
    components, _ = connected_components(tri_graph, directed=False)
    return SurfaceCheck(surface.name, n_tri, int(np.count_nonzero(counts == 1)), int(np.count_nonzero(counts > 2)),
                        nonmanifold_vertices, misoriented, int(components), surface.volume_mm3)


def _corner_id(triangles: np.ndarray, which: np.ndarray, vertex: np.ndarray) -> np.ndarray:
    """Index 3 t + c of the corner c of triangle t that is ``vertex``."""
    column = np.argmax(triangles[which] == vertex[:, None], axis=1)
    return 3 * which + column
