"""A skin layer on a mesh coarser than the skin: each element's share of the layer of given
thickness under the skin surface, for partial-volume weighting of its material.

Skin is about 1.5-2 mm thick and some 5-20 times stiffer than the tissue beneath it (suction
tests: ~56 kPa vs ~3 kPa). A fitting mesh of 4-10 mm cannot hold an element through that
thickness, so the elements that straddle the layer carry the skin's stiffness in proportion to
the part of their volume inside it (:meth:`~BreastBiomechLib.solver.materials.ElementMaterials.
with_skin`). Where the mesh is finer than the layer the shares are 1 inside it and 0 below, and
the weighting is the layer itself; a mesh with skin elements (tissue label ``skin``) needs none
of this. Positions in LPS mm.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces

_LATTICE = 8  # quadrature lattice per tet edge: (n+1)(n+2)(n+3)/6 = 165 points per element


def _lattice_weights(n: int = _LATTICE) -> np.ndarray:
    """Barycentric coordinates (P, 4) of the centres of a regular subdivision of a tet: the
    sample points whose share below a level approximates a volume fraction."""
    points = [(i, j, k) for i in range(n) for j in range(n - i) for k in range(n - i - j)]
    bary = np.array([[i + 0.25, j + 0.25, k + 0.25] for i, j, k in points]) / n
    return np.column_stack([1.0 - bary.sum(axis=1), bary])


def surface_distance(mesh: TetMesh, skin_nodes, spacing_mm: float = 0.5) -> np.ndarray:
    """Distance (N,) mm of every node from the skin surface: the boundary faces whose three
    nodes are all ``skin_nodes``, each sampled every ``spacing_mm`` along its edges (so that a
    node's distance is to the surface, not only to its vertices, within a quarter of that)."""
    skin = np.zeros(len(mesh.nodes), bool)
    skin[np.asarray(skin_nodes, dtype=np.int64)] = True
    faces, _ = boundary_faces(mesh.tets)
    faces = faces[skin[faces].all(axis=1)]
    if len(faces) == 0:
        raise ValueError("no boundary face lies on the skin: give the skin surface's nodes (e.g. the 'skin' or "
                         "'breast_skin' node set)")
    corners = mesh.nodes[faces]
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    divisions = np.maximum(1, np.ceil(longest / spacing_mm)).astype(int)  # each face by its own size
    samples = []
    for n in np.unique(divisions):
        grid = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)], float) / n
        weights = np.column_stack([1.0 - grid.sum(axis=1), grid])
        samples.append(np.einsum("pk,fkd->fpd", weights, corners[divisions == n]).reshape(-1, 3))
    return cKDTree(np.concatenate(samples)).query(mesh.nodes, workers=-1)[0]  # on every core: deep nodes query slowly


def skin_fraction(mesh: TetMesh, skin_nodes, thickness_mm: float, depth_mm: np.ndarray | None = None) -> np.ndarray:
    """Each element's share (M,) in [0, 1] of its volume within ``thickness_mm`` of the skin
    surface (the distance linear over the element, its share counted on a 165-point lattice).
    ``depth_mm``: the nodes' :func:`surface_distance` from ``skin_nodes`` where it is known
    (shares at several thicknesses measure it once)."""
    if not (np.isfinite(thickness_mm) and thickness_mm > 0):
        raise ValueError(f"the skin thickness must be a positive number of millimetres, not {thickness_mm}")
    depth = surface_distance(mesh, skin_nodes) if depth_mm is None else depth_mm
    inside = (_lattice_weights() @ depth[mesh.tets].T) < thickness_mm  # (P, M)
    return inside.mean(axis=0)


def check_thickness(mesh: TetMesh, skin_nodes, thickness_mm: float) -> None:
    """Refuse a skin thicker than the breast beneath it (the deepest node's distance from the
    skin), naming both."""
    deepest = float(surface_distance(mesh, skin_nodes).max())
    if thickness_mm >= deepest:
        raise ValueError(f"a skin of {thickness_mm:g} mm is as thick as the breast is deep ({deepest:.1f} mm from "
                         "the skin at most); the skin is 1-3 mm thick")
