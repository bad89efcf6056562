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
