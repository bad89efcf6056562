"""Absolute moduli from a measured plate force: with the plates' travel prescribed the equilibrium
depends only on the moduli's ratios (every stiffness doubled: the same displacement, twice the
plate forces), so a measured force fixes the scale a fit cannot see; the weighted least squares
over states and what a model with gravity or springs refuses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from BreastBiomechLib.io.case_layout import PlateForce
from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace
from BreastBiomechLib.optimisation.force_scale import ForceScale, force_scale, not_scale_free, predicted_force
from BreastBiomechLib.optimisation.synthetic import synthetic_case
from BreastBiomechLib.solver import DynamicRelaxation, solve_batch

RELAXATION = DynamicRelaxation(load_iterations=400, tolerance_mm=0.002)


def test_every_stiffness_scaled_leaves_the_displacement_and_scales_the_plate_forces():
    case = synthetic_case((40.0, 35.0, 40.0), element_mm=8.0, voxel_mm=(3.0, 3.0, 3.0))
    space = ParameterSpace.for_model("iso-hetero", ["fat", "glandular"], free=("E",))
    problem = FittingProblem(space, case.mesh, case.undeformed, case.undeformed, case.planes, relaxation=RELAXATION,
                             device="cpu")
    materials = space.element_materials(space.unit({"glandular.E": 30e3}), problem.tissue)
    doubled = replace(materials, mu=2.0 * materials.mu, kappa=2.0 * materials.kappa, eta=2.0 * materials.eta)
    base, stiff = solve_batch(problem.model, [materials, doubled], device="cpu", relaxation=RELAXATION)
    assert base.ok and stiff.ok
    assert np.abs(stiff.displacement - base.displacement).max() < 5 * RELAXATION.tolerance_mm
    np.testing.assert_allclose(stiff.plate_normal_forces, 2.0 * base.plate_normal_forces, rtol=0.02)
    plates = problem.model.loading.plates
    predicted = predicted_force(base, plates, plates[1].name)
    assert predicted == pytest.approx(base.plate_normal_forces[1]) and predicted > 0
    # the doubled model's force, measured with an sd, gives the scale 2 at the base moduli
    scale = force_scale({"compressed": (PlateForce(float(stiff.plate_normal_forces[1]), 0.1, plates[1].name),
                                        predicted)})
    assert scale.scale == pytest.approx(2.0, rel=0.02) and scale.sd == pytest.approx(0.1 / predicted)
    absolute = scale.materials({"fat": {"E": 10e3, "nu": 0.49, "eta": 1e3}})
    assert absolute["fat"] == pytest.approx({"E": 10e3 * scale.scale, "nu": 0.49, "eta": 1e3 * scale.scale})
    with pytest.raises(ValueError, match="the fit's plates are"):
        predicted_force(base, plates, "anterior")
    # gravity or springs in the model: its forces do not scale with the moduli
    assert not_scale_free(problem.model) == ""
    heavy = replace(problem.model, loading=replace(problem.model.loading, gravity=np.array([0.0, -9.81, 0.0])))
    assert "gravity" in not_scale_free(heavy)


def test_the_scale_weighs_each_state_by_its_force_s_precision():
    records = {"a": (PlateForce(10.0, 1.0), 5.0), "b": (PlateForce(30.0, 2.0), 10.0)}
    scale = force_scale(records)
    weights = np.array([5.0 ** 2 / 1.0, 10.0 ** 2 / 4.0])
    assert scale.scale == pytest.approx((10.0 * 5.0 / 1.0 + 30.0 * 10.0 / 4.0) / weights.sum())
    assert scale.sd == pytest.approx(1.0 / np.sqrt(weights.sum()))
    assert scale.states["b"] == {"measured_N": 30.0, "sd_N": 2.0, "plate": None, "predicted_N": 10.0}
    assert isinstance(scale, ForceScale)
    with pytest.raises(ValueError, match="no press on the tissue"):
        force_scale({"a": (PlateForce(10.0, 1.0), 0.0)})
    with pytest.raises(ValueError, match="no measured plate force"):
        force_scale({})
