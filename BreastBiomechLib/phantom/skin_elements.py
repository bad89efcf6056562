"""A phantom truth's skin as explicit elements: the truth mesh's elements whose centroids lie
within the skin's thickness of the skin surface become skin (tissue label ``skin``, the truth's
skin material), on a truth mesh whose surface is fine enough to hold the layer
(:func:`skin_surface_edge_mm`).

This is the hidden truth's implementation, kept apart from the discrepancy workflow's skin
candidate (:mod:`BreastBiomechLib.discrepancy.effects.skin`, partial-volume weighting of
coarse elements by :mod:`BreastBiomechLib.mesh.skin`): a suite whose truths were made by the
candidates' own code would measure how well a candidate matches its generator, not the
physical effect (issue 77, point 5). Here the depth is the exact distance of each element's
centroid to the nearest skin triangle, and an element is skin or not (no weighting).
Positions in LPS mm.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from BreastBiomechLib.labels import MUSCLE, SKIN
from BreastBiomechLib.mesh.distance import point_triangle_distance
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces

LAYERS = 1.5  # a truth skin's thickness over the size of the skin triangles of the mesh that holds it
FINEST_SURFACE_MM = 1.0  # the finest skin triangles a truth mesh is made with (a 1 mm skin)


def skin_surface_edge_mm(edge_mm: float, thickness_mm: float) -> float:
    """The truth mesh's skin triangle size (mm) for a skin of ``thickness_mm`` on a mesh of
    ``edge_mm``: the thickness over :data:`LAYERS`, at least :data:`FINEST_SURFACE_MM`, at most
    the mesh's own size, so that the surface elements are thinner than the skin."""
    return float(min(edge_mm, max(FINEST_SURFACE_MM, thickness_mm / LAYERS)))


def _skin_faces(mesh: TetMesh, skin_set: str) -> np.ndarray:
    """The boundary triangles (F, 3) whose three nodes are in node set ``skin_set``."""
    skin = np.zeros(len(mesh.nodes), bool)
    skin[mesh.node_set(skin_set)] = True
    faces, _ = boundary_faces(mesh.tets)
    return faces[skin[faces].all(axis=1)]


def depth_below_skin(mesh: TetMesh, points: np.ndarray, skin_set: str = "skin", candidates: int = 12) -> np.ndarray:
    """Exact distance (N,) mm of ``points`` (N, 3) to the mesh's skin surface: its boundary
    triangles whose three nodes are in node set ``skin_set``; each point against the
    ``candidates`` triangles whose centroids are nearest, which holds the nearest triangle for
    a surface of well-shaped triangles."""
    faces = _skin_faces(mesh, skin_set)
    if len(faces) == 0:
        raise ValueError(f"the truth mesh has no boundary triangle in its {skin_set!r} node set: it holds no skin "
                         "surface to lay a skin under")
    corners = mesh.nodes[faces]
    k = min(candidates, len(faces))
    _, nearest = cKDTree(corners.mean(axis=1)).query(points, k=k)
    nearest = nearest.reshape(len(points), k)
    depth = np.full(len(points), np.inf)
    for j in range(k):
        tri = corners[nearest[:, j]]
        depth = np.minimum(depth, point_triangle_distance(points, tri[:, 0], tri[:, 1], tri[:, 2]))
    return depth


def with_skin_elements(mesh: TetMesh, thickness_mm: float) -> TetMesh:
    """``mesh`` with its elements whose centroids lie within ``thickness_mm`` of the skin surface
    (muscle excepted) labelled ``skin``; the thickness the elements hold is rounded by the mesh's
    size (:func:`skin_layer_figures`)."""
    if not (np.isfinite(thickness_mm) and thickness_mm > 0):
        raise ValueError(f"the skin thickness must be a positive number of millimetres, not {thickness_mm}")
    tissue = np.asarray(mesh.cell_data["tissue"]).copy()
    layer = (depth_below_skin(mesh, mesh.nodes[mesh.tets].mean(axis=1)) < thickness_mm) & (tissue != MUSCLE.label)
    if not layer.any():
        raise ValueError(f"no element's centroid lies within {thickness_mm:g} mm of the skin: the truth mesh is too "
                         "coarse for this skin; make its skin triangles finer (skin_surface_edge_mm)")
    tissue[layer] = SKIN.label
    return TetMesh(mesh.nodes, mesh.tets, dict(mesh.point_data), {**mesh.cell_data, "tissue": tissue})


def skin_layer_figures(mesh: TetMesh) -> dict:
    """The skin elements of ``mesh``: how many, their volume (cm^3) and the thickness they hold
    (their volume over the skin surface's area, mm)."""
    layer = np.asarray(mesh.cell_data["tissue"]) == SKIN.label
    c = mesh.nodes[mesh.tets[layer]]
    volume = float(np.abs(np.einsum("ij,ij->i", c[:, 1] - c[:, 0],
                                    np.cross(c[:, 2] - c[:, 0], c[:, 3] - c[:, 0]))).sum() / 6.0)
    f = mesh.nodes[_skin_faces(mesh, "skin")]
    area = float(0.5 * np.linalg.norm(np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]), axis=1).sum())
    return {"elements": int(layer.sum()), "volume_cm3": volume / 1e3, "effective_thickness_mm": volume / area}
