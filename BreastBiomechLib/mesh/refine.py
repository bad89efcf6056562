"""Uniform (nested) refinement of tetrahedral meshes, for convergence studies.

Nodes in millimetres (LPS)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_nodes
from BreastBiomechLib.rows import unique_rows

_EDGES = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
# the eight children of a tet in terms of its corners 0-3 and edge midpoints 4-9 (order of _EDGES):
# four corner tets and the inner octahedron cut along its 02-13 diagonal
_CHILDREN = np.array([(0, 4, 5, 6), (4, 1, 7, 8), (5, 7, 2, 9), (6, 8, 9, 3),
                      (4, 5, 6, 8), (4, 5, 7, 8), (5, 6, 8, 9), (5, 7, 8, 9)])


def _edges(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unique edges (E, 2) of ``tets`` (each sorted) and, for each tet's six edges in the order
    of ``_EDGES``, its index among them (M * 6,)."""
    edges = np.sort(tets[:, _EDGES].reshape(-1, 2), axis=1)
    unique, inverse = unique_rows(edges, return_inverse=True)
    return unique, inverse


def midpoint_edges(mesh: TetMesh) -> np.ndarray:
    """The edge (E, 2) whose midpoint each new node of :func:`refine_uniform` is, in the order of
    the new node ids (``len(mesh.nodes) + e``)."""
    return _edges(mesh.tets)[0]


def refine_uniform(mesh: TetMesh, project: Callable[[np.ndarray], np.ndarray] | None = None) -> TetMesh:
    """Split every tet into eight at its edge midpoints (edge lengths halve; the coarse nodes are
    kept with their ids first, then the midpoints in the order of :func:`midpoint_edges`; tet
    i's eight children are tets 8i to 8i + 7). ``project`` maps the new boundary nodes (K, 3) mm onto the exact
    surface they approximate, so the geometry converges with the mesh. Point and cell data are
    not carried over (recompute node sets on the refined mesh)."""
    tets = mesh.tets
    n = len(mesh.nodes)
    unique, inverse = _edges(tets)
    mid_ids = n + inverse.reshape(-1, 6)
    nodes = np.concatenate([mesh.nodes, 0.5 * (mesh.nodes[unique[:, 0]] + mesh.nodes[unique[:, 1]])])
    local = np.concatenate([tets, mid_ids], axis=1)  # (M, 10)
    children = local[:, _CHILDREN].reshape(-1, 4)
    if project is not None:
        new_boundary = np.flatnonzero(boundary_nodes(children, len(nodes))[n:]) + n
        nodes[new_boundary] = project(nodes[new_boundary])
    refined = TetMesh(nodes, children)
    negative = refined.volumes < 0
    children[negative] = children[negative][:, [0, 2, 1, 3]]
    return TetMesh(nodes, children)
