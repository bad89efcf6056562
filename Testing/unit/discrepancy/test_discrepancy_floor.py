"""The measured model-error floor's parts: grouping the discretisation estimate into a floor per
region and channel, the noise model that takes it, and the refined solve started from the coarse
solution (the whole floor: Testing/integration/test_discrepancy.py's null case; the refinement:
Testing/unit/solver/test_refinement.py)."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.floor import MeasuredFloor, floor_of
from BreastBiomechLib.discrepancy.observations import NoiseModel, Observations


def test_a_feature_s_floor_is_its_group_s_rms_never_below_the_lower_bound():
    error = np.array([0.3, -0.4, 1.2, -1.6, 0.1])
    groups = np.array(["contact (landmarks)"] * 2 + ["contact (surface)"] * 2 + ["fat (surface)"])
    floor, summary = floor_of(error, groups, 0.5)
    np.testing.assert_allclose(floor, [0.5, 0.5, np.sqrt(2.0), np.sqrt(2.0), 0.5])  # 0.354 -> 0.5; 1.414; 0.1 -> 0.5
    assert summary["contact (surface)"] == {"features": 2, "rms_mm": pytest.approx(np.sqrt(2.0))}
    record = MeasuredFloor(floor, error, summary, 0.5, (100, 800), 1.0, groups).to_dict()
    lower = MeasuredFloor.from_dict(record, 0.1)  # another lower bound: the same estimate, another floor
    np.testing.assert_allclose(lower.floor, [np.sqrt(0.125), np.sqrt(0.125), np.sqrt(2.0), np.sqrt(2.0), 0.1])
    assert lower.tets == (100, 800) and lower.summary()["largest"]["group"] == "contact (surface)"


def test_the_noise_model_takes_each_feature_s_floor():
    """sigma = sqrt(measurement^2 + floor^2), the fixed floor replaced feature by feature; the
    measurement's part kept apart; a floor of the wrong length or no measurement part refused."""
    measurement = np.array([0.5, 0.5, 0.29])
    fixed = Observations(["a L", "a P", "skin node 3"], np.array(["landmarks", "landmarks", "surface"]), np.zeros(3),
                         np.hypot(measurement, 0.5), np.zeros((3, 3)), [], 0.5, measurement)
    np.testing.assert_allclose(fixed.feature_floor, 0.5)
    np.testing.assert_allclose(fixed.base_sigma, fixed.sigma)
    measured = fixed.with_floor(np.array([0.5, 1.5, 0.7]))
    np.testing.assert_allclose(measured.sigma, np.hypot(measurement, [0.5, 1.5, 0.7]))
    np.testing.assert_allclose(measured.feature_floor, [0.5, 1.5, 0.7])
    np.testing.assert_allclose(measured.base_sigma, fixed.sigma)  # what an effect's share is weighted by
    with pytest.raises(ValueError, match="a floor for 3 features"):
        fixed.with_floor(np.ones(2))
    with pytest.raises(ValueError, match="measured.*fixed"):
        NoiseModel(floor="guessed")


def test_the_refined_model_relaxed_from_the_coarse_solution_ends_where_it_does_from_rest():
    """A plate compression of a coarse hemi-ellipsoid, refined: relaxed from its coarse solution
    carried onto the refined nodes, it reaches the equilibrium it reaches from rest (within the
    relaxation's tolerance, far below the refinement's own change) in fewer iterations; with
    friction (the equilibrium depends on the path) it is not started warm."""
    from dataclasses import replace

    from BreastBiomechLib.discrepancy.floor import warm_refined_solve
    from BreastBiomechLib.solver import DynamicRelaxation, solve_batch
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
    from BreastBiomechLib.solver.refinement import Refinement

    relaxation = DynamicRelaxation(tolerance_mm=0.01)
    coarse = hemi_ellipsoid_compression(18.0, compression=0.2)  # a stair-stepped coarse grid: the
    # refinement moves nodes by up to 18 mm (2026-12-06), a start far from the refined equilibrium
    [solution] = solve_batch(coarse, [coarse.materials], device="cpu", relaxation=relaxation)
    refinement = Refinement(coarse.mesh)
    fine = refinement.model(coarse, coarse.materials, coarse.loading.plates)
    [cold] = solve_batch(fine, [fine.materials], device="cpu", relaxation=relaxation)
    start = refinement.node_values(solution.displacement)
    warm = warm_refined_solve(fine, start, relaxation, "cpu")
    assert cold.ok and warm.ok
    change = np.abs(cold.displacement - start).max()
    assert np.abs(warm.displacement - cold.displacement).max() < min(0.05, 0.1 * change)
    rough = replace(fine, loading=replace(fine.loading, plates=[replace(p, friction=0.3) for p in fine.loading.plates]))
    assert warm_refined_solve(rough, start, relaxation, "cpu") is None


def test_a_landmark_outside_a_coarse_mesh_moves_on_its_refinement_as_on_the_mesh():
    """The floor's refined solve moves the landmarks on the refined mesh, whose surface is the
    fitting mesh's: a landmark the fitting mesh's tolerance admits (here 8 mm outside an 18 mm
    stair-stepped mesh) is mapped there too, not refused for the refined mesh's halved edges, and
    a linear displacement field moves it exactly as the fitting mesh does."""
    from BreastBiomechLib.discrepancy.floor import refined_landmarks
    from BreastBiomechLib.landmarks import Landmarks, locate_points, map_landmarks
    from BreastBiomechLib.landmarks.mapping import outside_tolerance_mm
    from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh
    from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_faces
    from BreastBiomechLib.solver.refinement import Refinement

    mesh = hemi_ellipsoid_mesh(spacing_mm=18.0)
    refinement = Refinement(mesh)
    refined = TetMesh(refinement.node_values(mesh.nodes), refinement.refined.tets)
    assert outside_tolerance_mm(refined) < 8.0 < outside_tolerance_mm(mesh)
    faces = boundary_faces(mesh.tets)[0]
    corners = mesh.nodes[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    k = int(np.argmax(corners[:, :, 2].mean(axis=1)))  # a face on the breast's front, away from the chest wall
    point = corners[k].mean(axis=0) + 8.0 * normals[k] / np.linalg.norm(normals[k])
    assert 5.0 < locate_points(mesh, point[None]).outside_mm[0] < outside_tolerance_mm(mesh)
    landmarks = Landmarks(point[None], ["nipple"])
    with pytest.raises(ValueError, match="outside the mesh"):  # the refined mesh's own tolerance
        map_landmarks(refined, np.zeros_like(refined.nodes), landmarks)
    linear = np.array([[0.1, 0.02, 0.0], [0.0, -0.05, 0.03], [0.01, 0.0, 0.08]])
    coarse = map_landmarks(mesh, mesh.nodes @ linear.T + [1.0, 2.0, 3.0], landmarks).positions
    fine = refined_landmarks(mesh, refinement, refined.nodes @ linear.T + [1.0, 2.0, 3.0], landmarks)
    np.testing.assert_allclose(fine, coarse, atol=1e-9)
    np.testing.assert_allclose(fine[0], point + linear @ point + [1.0, 2.0, 3.0], atol=1e-9)
