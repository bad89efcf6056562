"""Exact Euclidean distances from points to triangles (LPS mm in, mm out): the closest point
by the Voronoi regions of a triangle's vertices, edges and face (Ericson, Real-Time Collision
Detection, 5.1.5), vectorised over pairs of a point and a triangle."""

from __future__ import annotations

import numpy as np


def point_triangle_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance (N,) of each point (N, 3) to its triangle (a, b, c: each (N, 3)): the closest
    point by the Voronoi regions of the triangle's vertices, edges and face."""
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp, cp = points - b, points - c
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denominator = va + vb + vc
        v_face, w_face = vb / denominator, vc / denominator
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    closest = a + v_face[:, None] * ab + w_face[:, None] * ac  # inside the face
    regions = [  # (where, closest point); a later entry wins, the reverse of the tests' usual order
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + t_bc[:, None] * (c - b)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[:, None] * ac),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[:, None] * ab),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for where, point in regions:
        closest = np.where(where[:, None], point, closest)
    return np.linalg.norm(points - closest, axis=1)
