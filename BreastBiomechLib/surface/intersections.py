"""Self-intersections of a triangulated surface: which pairs of triangles cross each other.

A closed surface handed to TetGen must not touch itself. Two triangles cross when an edge of one
passes through the inside of the other; triangles that share a vertex or an edge are tested with
the shared corner left out, so a fold at a vertex counts and the shared corner does not. Exact
touching (an edge passing exactly through another triangle's edge) has zero measure and is not
reported. Coordinates in any frame; the tolerance is relative to the triangles' size."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from BreastBiomechLib.surface.trisurface import TriSurface

_EPS = 1e-9


class SurfaceCrossesItself(ValueError):
    """A surface that must be closed and free of self-intersections (the body surface TetGen
    meshes) crosses itself."""


def _segment_crosses(p0: np.ndarray, p1: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(K,) whether segments p0->p1 (K, 3) pass through the inside of triangles tri (K, 3, 3)
    (Moller-Trumbore with the segment's ends and the triangle's border left out)."""
    direction = p1 - p0
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(direction, e2)
    a = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(direction, axis=1)
    ok = np.abs(a) > 1e-12 * np.maximum(scale, 1e-300)  # not parallel
    f = np.where(ok, 1.0 / np.where(ok, a, 1.0), 0.0)
    s = p0 - tri[:, 0]
    u = f * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = f * np.einsum("ij,ij->i", direction, q)
    t = f * np.einsum("ij,ij->i", e2, q)
    return ok & (u > _EPS) & (v > _EPS) & (u + v < 1 - _EPS) & (t > _EPS) & (t < 1 - _EPS)


def _candidate_pairs(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Pairs (K, 2) of triangles whose bounding spheres (about the centroid) overlap."""
    corners = points[triangles]
    centroids = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centroids[:, None], axis=2).max(axis=1)
    pairs = cKDTree(centroids).query_pairs(2.0 * float(radius.max()), output_type="ndarray")
    if len(pairs) == 0:
        return pairs.reshape(0, 2)
    gap = np.linalg.norm(centroids[pairs[:, 0]] - centroids[pairs[:, 1]], axis=1)
    return pairs[gap <= radius[pairs[:, 0]] + radius[pairs[:, 1]]]


def intersecting_pairs(surface: TriSurface) -> np.ndarray:
    """Pairs (K, 2) of triangle indices of ``surface`` that cross each other (see the module)."""
    tri = np.asarray(surface.triangles)
    points = np.asarray(surface.points, float)
    if len(tri) < 2:
        return np.zeros((0, 2), np.int64)
    pairs = _candidate_pairs(points, tri)
    if len(pairs) == 0:
        return pairs.astype(np.int64)
    a, b = tri[pairs[:, 0]], tri[pairs[:, 1]]
    shared = (a[:, :, None] == b[:, None, :]).any(axis=2).sum(axis=1)
    pairs, a, b = pairs[shared < 2], a[shared < 2], b[shared < 2]  # edge neighbours: a fold shows at the other pairs
    crossing = np.zeros(len(pairs), bool)
    for first, second in ((a, b), (b, a)):
        tri_other = points[second]
        for k in range(3):
            crossing |= _segment_crosses(points[first[:, k]], points[first[:, (k + 1) % 3]], tri_other)
    return pairs[crossing].astype(np.int64)


def intersecting_vertices(surface: TriSurface) -> np.ndarray:
    """Indices of the vertices of every triangle in a crossing pair (empty when none)."""
    pairs = intersecting_pairs(surface)
    return np.unique(np.asarray(surface.triangles)[pairs.ravel()]) if len(pairs) else np.zeros(0, np.int64)
