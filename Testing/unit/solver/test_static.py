"""The static Newton reference (solver/static.py): its forces and tangent are the explicit
solver's discretisation, it reproduces the analytic block compression, and the explicit paths
(dynamic relaxation, settled physical time) end where it does."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import Constraint, DynamicRelaxation, ElementMaterials, Loading, Material, Model, solve
from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression
from BreastBiomechLib.solver.static import Discretisation, solve_static
from BreastBiomechLib.solver.tled import internal_forces

from test_solver import E, NU, SIDE, _block, _compression_model, analytic_uniaxial


def _random_state(formulation, seed=0):
    model = hemi_ellipsoid_compression(15.0, formulation=formulation)
    model.materials = ElementMaterials.uniform(len(model.mesh.tets),
                                               Material(E=10e3, nu=0.49, eta=3e3, fibre=(0.6, 0.8, 0.0)))
    rng = np.random.default_rng(seed)
    return model, rng.normal(size=model.mesh.nodes.shape) * 0.5, rng  # mm


@pytest.mark.parametrize("formulation", ["T4", "T4ANP"])
def test_forces_are_the_kernels_forces_and_the_tangent_is_their_derivative(formulation):
    model, u, rng = _random_state(formulation)
    disc = Discretisation(model)
    f = disc.forces(u * 1e-3)
    np.testing.assert_allclose(f, internal_forces(model, u, device="cpu"), atol=1e-5 * np.abs(f).max())
    K, G, H = disc.tangent(u * 1e-3)
    assert (G is None) == (formulation == "T4")
    v = rng.normal(size=u.shape) * 1e-7  # m
    central = (disc.forces(u * 1e-3 + v) - disc.forces(u * 1e-3 - v)).ravel() / 2
    Kv = K @ v.ravel() + (G @ (H @ v.ravel()) if G is not None else 0.0)
    assert np.abs(Kv - central).max() < 1e-7 * np.abs(central).max()


def test_static_block_compression_matches_the_analytic_solution():
    mesh = _block()
    s = solve_static(_compression_model(mesh, Material(E, NU)), increments=4)
    assert s.ok, s.message
    l1, l2, P33 = analytic_uniaxial(0.7)
    corner = np.argmax(mesh.nodes.sum(axis=1))
    assert 1 + s.displacement[corner, 0] / SIDE == pytest.approx(l1, rel=1e-6)
    assert 1 + s.displacement[corner, 1] / SIDE == pytest.approx(l2, rel=1e-6)
    assert s.plate_forces[1, 2] == pytest.approx(P33 * (SIDE * 1e-3) ** 2, rel=1e-5)
    assert s.plate_forces[0, 2] == pytest.approx(-P33 * (SIDE * 1e-3) ** 2, rel=1e-5)


def test_plates_release_nodes_they_would_pull():
    """A block on a fixed plate, its top pulled up: no node stays on the plate (it would have to
    pull), whichever set the solve starts from."""
    mesh = box_mesh((SIDE, SIDE, SIDE), (3, 3, 3))
    base = _compression_model(mesh, Material(E, NU), strain=0.0)
    top = np.flatnonzero(mesh.point_data["face_zhi"])
    lifted = Loading(base.loading.constraints + [Constraint(top, (False, False, True), [0.0, 0.0, 2.0])],
                     base.loading.plates[:1])
    model = Model(mesh, base.materials, lifted)
    s = solve_static(model, increments=2)
    assert s.ok, s.message
    assert np.all(s.displacement[np.flatnonzero(mesh.point_data["face_zlo"]), 2] > 0.1)
    assert np.allclose(s.plate_forces, 0.0)
    again = solve_static(model, initial_displacement=np.zeros_like(mesh.nodes))  # every bottom node starts active
    assert again.ok and np.abs(again.displacement - s.displacement).max() < 1e-6


def test_models_that_cannot_be_solved_say_why():
    mesh = box_mesh((SIDE, SIDE, SIDE), (2, 2, 2))
    free_block = Model(mesh, ElementMaterials.uniform(len(mesh.tets), Material(E, NU)), Loading(gravity=[0, 0, -9.81]))
    s = solve_static(free_block, increments=1)
    assert s.status == "singular" and "rigid motion" in s.message
    with pytest.raises(ValueError, match="increments"):
        solve_static(free_block, increments=2, initial_displacement=np.zeros_like(mesh.nodes))
    bottom = np.flatnonzero(mesh.point_data["face_zlo"])
    top = np.flatnonzero(mesh.point_data["face_zhi"])
    crushed = Model(mesh, free_block.materials,
                    Loading([Constraint.fixed(bottom), Constraint(top, (False, False, True), [0, 0, -12.0])]))
    s = solve_static(crushed, increments=1, max_cuts=1)
    assert s.status in ("inverted elements", "not converged") and "of the initial increment" in s.message


def test_dynamic_relaxation_and_gravity_reach_the_static_solution():
    """A soft block hanging under gravity (fixed at the top), stiffer in its upper half: the
    fictitious masses of dynamic relaxation (heavier in the stiff half) must not change the weight."""
    mesh = box_mesh((SIDE, SIDE, 3 * SIDE), (2, 2, 6))
    top = np.flatnonzero(mesh.point_data["face_zhi"])
    upper = (mesh.nodes[mesh.tets].mean(axis=1)[:, 2] > 1.5 * SIDE).astype(int)
    materials = ElementMaterials.from_tissues(upper, {0: Material(1e3, 0.45), 1: Material(5e3, 0.45)})
    model = Model(mesh, materials, Loading([Constraint.fixed(top)], gravity=[0, 0, -9.81]))
    static = solve_static(model, increments=2)
    relaxed = solve(model, device="cpu", relaxation=DynamicRelaxation(tolerance_mm=1e-4))
    assert static.ok and relaxed.ok, relaxed.message
    assert static.displacement[:, 2].min() < -0.5  # a visible sag
    assert np.abs(relaxed.displacement - static.displacement).max() < 2e-3


def test_explicit_paths_end_at_the_static_solution_on_a_tetgen_breast():
    """Issue 7's check on a smooth (TetGen) breast, 25 % compression: the settled physical-time
    solve, the same with mass scaling (7x fewer steps) and dynamic relaxation all end within
    0.1 mm of the static Newton solution (observed 0.001, 0.0006 and 0.005 mm), with the same
    plate forces. TetGen's slivers make the stable step small
    (7e-5 s here): before the compensated increment form, float32 physical-time runs of such
    meshes stalled short of equilibrium (0.13 mm at 4k tets, 0.8 mm at 22k tets)."""
    model = hemi_ellipsoid_compression(12.0, smooth=True, settle_time=2.0)
    static = solve_static(model)
    physical = solve(model, device="cpu", steady_state_mm=0.001)
    relaxed = solve(model, device="cpu", relaxation=DynamicRelaxation(tolerance_mm=0.01))
    scaled = solve(model, device="cpu", steady_state_mm=0.001, mass_scaling=True)
    assert static.ok and physical.ok and relaxed.ok and scaled.ok, (physical.message, relaxed.message)
    assert scaled.steps < physical.steps / 3 and "mass scaling: total mass x" in scaled.message
    for explicit, limit in ((physical, 0.01), (relaxed, 0.03), (scaled, 0.01)):
        assert np.linalg.norm(explicit.displacement - static.displacement, axis=1).max() < limit
        np.testing.assert_allclose(explicit.plate_forces, static.plate_forces, rtol=1e-3, atol=1e-3)
