"""Exact distances from points to triangles (mesh.distance): the phantom's skin layer and the
landmark mapping use them."""

from __future__ import annotations

import numpy as np
import pytest


def test_the_distance_to_a_triangle_is_exact():
    """Against a dense sampling of each triangle: never below the exact distance (no point of the
    triangle is nearer) and within the sampling's resolution of it, for points in every Voronoi
    region (vertices, edges, face; above and beside)."""
    from BreastBiomechLib.mesh.distance import point_triangle_distance

    rng = np.random.default_rng(3)
    n = 200
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    points = 2.0 * rng.normal(size=(n, 3))
    exact = point_triangle_distance(points, a, b, c)
    s = np.linspace(0.0, 1.0, 201)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1.0
    u, v = u[keep], v[keep]
    sampled = np.array([np.linalg.norm(a[i] + np.outer(u, b[i] - a[i]) + np.outer(v, c[i] - a[i]) - points[i],
                                       axis=1).min() for i in range(n)])
    assert np.all(sampled >= exact - 1e-12)
    assert np.abs(sampled - exact).max() < 0.05
    assert point_triangle_distance(a, a, b, c) == pytest.approx(np.zeros(n), abs=1e-12)  # the vertices themselves
