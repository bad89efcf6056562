"""Landmarks moved through an FE displacement (exact for affine fields) and their errors."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.landmarks import Landmarks, landmark_errors, locate_points, map_landmarks
from BreastBiomechLib.mesh.primitives import box_mesh


@pytest.fixture(scope="module")
def mesh():
    return box_mesh((40.0, 30.0, 20.0), (5, 4, 3), origin_mm=(-20.0, -15.0, -10.0))


def test_mapping_is_exact_for_an_affine_displacement(mesh):
    rng = np.random.default_rng(0)
    inside = rng.uniform([-19, -14, -9], [19, 14, 9], (25, 3))
    edge = np.array([[20.0, 0.0, 0.0], [-20.0, -15.0, -10.0]])  # on a face and at a corner
    points = np.vstack([inside, edge, [[0.0, 0.0, 10.8]]])      # and 0.8 mm above the top face
    marks = Landmarks(points, [f"P{i}" for i in range(len(points))])
    matrix = np.array([[0.8, 0.1, 0.0], [0.0, 1.1, -0.05], [0.03, 0.0, 1.2]])
    shift = np.array([1.0, -2.0, 0.5])
    moved = map_landmarks(mesh, mesh.nodes @ (matrix - np.eye(3)).T + shift, marks)
    np.testing.assert_allclose(moved.positions, points @ matrix.T + shift, atol=1e-9)
    assert moved.labels == marks.labels
    where = locate_points(mesh, points)
    assert np.all(where.outside_mm[:-1] == 0)
    assert where.outside_mm[-1] == pytest.approx(0.8)
    np.testing.assert_allclose(where.weights.sum(axis=1), 1.0)


def test_landmarks_far_outside_are_refused(mesh):
    marks = Landmarks([[0.0, 0.0, 30.0]], ["far"])
    with pytest.raises(ValueError, match=r"far \(20.0 mm\)"):
        map_landmarks(mesh, np.zeros_like(mesh.nodes), marks)
    with pytest.raises(ValueError, match="one 3-vector per node"):
        map_landmarks(mesh, np.zeros((2, 3)), marks)


def test_errors_follow_the_seeds_table_2():
    reference = Landmarks([[0, 0, 0], [10, 0, 0], [0, 10, 0]], ["A", "B", "C"])
    measured = Landmarks([[0, 0, 3], [10, 0, 4], [0, 10, 0]], ["A", "B", "C"])
    predicted = Landmarks([[0, 0, 2], [10, 0, 4], [0, 13, 4], [5, 5, 5]], ["A", "B", "C", "extra"])
    errors = landmark_errors(reference, predicted, measured)
    assert errors.labels == ["A", "B", "C"]
    np.testing.assert_allclose(errors.displacement_mm, [3, 4, 0])
    np.testing.assert_allclose(errors.error_mm, [1, 0, 5])
    summary = errors.summary()
    assert summary["error_mm"] == pytest.approx({"mean": 2.0, "sd": np.std([1, 0, 5]), "max": 5.0})
    with pytest.raises(ValueError, match="share no label"):
        landmark_errors(reference, Landmarks([[0, 0, 0]], ["Z"]), measured)


def test_points_are_found_in_the_tet_a_search_of_every_tet_gives():
    """The nearest-centroid search finds, for points inside, on nodes and outside, the tet the
    search over every tet finds (the deepest holding one, the lowest numbered on a tie)."""
    fine = box_mesh((40.0, 30.0, 20.0), (10, 8, 5), origin_mm=(-20.0, -15.0, -10.0))  # 2400 tets: more than tried first
    rng = np.random.default_rng(3)
    points = np.vstack([rng.uniform([-19.9, -14.9, -9.9], [19.9, 14.9, 9.9], (300, 3)), fine.nodes[::7],
                        [[0.0, 0.0, 12.0], [25.0, 3.0, 0.0]]])
    where = locate_points(fine, points)
    corners = fine.nodes[fine.tets]
    inverse = np.linalg.inv(np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1)))
    for k, p in enumerate(points[:-2]):
        b = np.einsum("mij,mj->mi", inverse, p - corners[:, 0])
        least = np.column_stack([1.0 - b.sum(axis=1), b]).min(axis=1)
        assert least[where.tets[k]] == pytest.approx(least.max(), abs=1e-12)
        assert where.outside_mm[k] == 0
    np.testing.assert_allclose(np.einsum("kc,kcd->kd", where.weights, corners[where.tets]), points, atol=1e-9)
    # a node lies in a tet that holds it, with all its weight on itself
    nodes = fine.nodes[::7]
    held = where.tets[300:300 + len(nodes)]
    assert np.all(np.isclose(where.weights[300:300 + len(nodes)].max(axis=1), 1.0))
    assert np.all(np.any(fine.tets[held] == np.arange(0, len(fine.nodes), 7)[:, None], axis=1))
    np.testing.assert_allclose(where.outside_mm[-2:], [2.0, 5.0], atol=1e-9)
