"""The solver renumbers a scattered mesh for the solve and answers in the mesh's own numbering
(solver/ordering.py): the same model, the same answer, messages that name the mesh's nodes and
elements."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh, hemi_ellipsoid_mesh
from BreastBiomechLib.solver import (Constraint, DynamicRelaxation, ElementMaterials, Loading, Material, Model, solve,
                                     solve_batch)
from BreastBiomechLib.solver import ordering
from BreastBiomechLib.solver.model import ReferenceState
from BreastBiomechLib.solver.ordering import SolverOrder, sectors_per_corner_read
from BreastBiomechLib.solver.warm import WarmStart
from test_solver import SIDE, _compression_model


@pytest.fixture
def any_size(monkeypatch):
    """Small meshes are renumbered too (the rule's size floor is for speed, not for correctness)."""
    monkeypatch.setattr(ordering, "MIN_ELEMENTS", 0)


def _shuffled(model: Model, seed: int = 0) -> tuple[Model, SolverOrder]:
    """``model`` with its nodes and elements numbered at random: the numbering a mesh generator
    may leave, the same model. ``order.nodes[i]`` is the original node of the shuffled node i."""
    rng = np.random.default_rng(seed)
    order = SolverOrder(rng.permutation(len(model.mesh.nodes)), rng.permutation(len(model.mesh.tets)))
    return order.model(model), order


def _compression(divisions=6, strain=0.2, formulation="T4ANP"):
    """test_solver's quarter-model cube (10 mm side) between a fixed and a moving plate."""
    return _compression_model(box_mesh((SIDE, SIDE, SIDE), (divisions,) * 3), Material(10e3, 0.45), strain,
                              formulation)


def test_only_scattered_meshes_of_some_size_are_renumbered():
    grid = hemi_ellipsoid_mesh((80.0, 70.0, 75.0), 4.0)  # a Kuhn grid: local as it is
    assert len(grid.tets) >= ordering.MIN_ELEMENTS
    assert sectors_per_corner_read(grid.tets) < ordering.SCATTERED_SECTORS
    assert SolverOrder.for_mesh(grid) is None
    scattered, _ = _shuffled(Model(grid, ElementMaterials.uniform(len(grid.tets), Material(10e3, 0.45)), Loading()))
    order = SolverOrder.for_mesh(scattered.mesh)
    assert order is not None and sectors_per_corner_read(scattered.mesh.tets) > ordering.SCATTERED_SECTORS
    assert SolverOrder.for_mesh(scattered.mesh, ordering.MAX_BATCH + 1) is None  # a batch shares the reads
    assert sectors_per_corner_read(order.tets(scattered.mesh.tets)) < 0.5 * sectors_per_corner_read(scattered.mesh.tets)
    assert sorted(order.nodes.tolist()) == list(range(len(grid.nodes)))
    assert sorted(order.elements.tolist()) == list(range(len(grid.tets)))
    small, _ = _shuffled(_compression())
    assert SolverOrder.for_mesh(small.mesh) is None  # below MIN_ELEMENTS


@pytest.mark.parametrize("relaxed", [False, True])
def test_a_renumbered_solve_answers_in_the_meshs_numbering(any_size, relaxed):
    """The same model numbered at random, solved (renumbered inside, since the numbering is
    scattered) in batch with another plate travel: the displacements of each node and the plate
    forces equal the solve in the original numbering to float32 round-off."""
    model = _compression()
    shuffled, order = _shuffled(model)
    assert SolverOrder.for_mesh(shuffled.mesh) is not None and SolverOrder.for_mesh(model.mesh) is None
    relaxation = DynamicRelaxation(load_iterations=300, tolerance_mm=0.001) if relaxed else None
    motions = [np.array([[0, 0, 0], [0, 0, -2.0]]), np.array([[0, 0, 0], [0, 0, -1.0]])]
    materials = [model.materials, ElementMaterials.uniform(len(model.mesh.tets), Material(20e3, 0.45))]
    plain = solve_batch(model, materials, plate_displacements=motions, device="cpu", relaxation=relaxation)
    renumbered = solve_batch(shuffled, [order.materials(m) for m in materials], plate_displacements=motions,
                             device="cpu", relaxation=relaxation)
    for a, b in zip(plain, renumbered):
        assert a.ok and b.ok, (a.message, b.message)
        assert np.abs(a.displacement).max() > 0.5
        np.testing.assert_allclose(b.displacement, a.displacement[order.nodes], atol=1e-4 if relaxed else 1e-5)
        np.testing.assert_allclose(b.plate_forces, a.plate_forces, rtol=1e-3, atol=1e-6)


def test_a_warm_start_and_a_prestate_are_read_in_the_meshs_numbering(any_size):
    model = _compression()
    shuffled, order = _shuffled(model)
    relaxation = DynamicRelaxation(load_iterations=300, tolerance_mm=0.001)
    start = solve(shuffled, device="cpu", relaxation=relaxation)
    softer = [ElementMaterials.uniform(len(model.mesh.tets), Material(8e3, 0.45))]
    cold = solve_batch(shuffled, softer, device="cpu", relaxation=relaxation)[0]
    warm = solve_batch(shuffled, softer, device="cpu", relaxation=relaxation,
                       warm_start=WarmStart.from_solution(start))[0]
    assert warm.ok and warm.steps < cold.steps
    np.testing.assert_allclose(warm.displacement, cold.displacement, atol=0.01)
    # a pre-stressed start (the compressed state, gravity on) in both numberings
    prestate = solve(model, device="cpu", relaxation=relaxation).displacement
    stressed = replace(model, prestate=ReferenceState(prestate, [0.0, 0.0, -9.81]))
    plain = solve(stressed, device="cpu")
    renumbered = solve(replace(shuffled, prestate=ReferenceState(prestate[order.nodes], [0.0, 0.0, -9.81])),
                       device="cpu")
    assert plain.ok and renumbered.ok
    np.testing.assert_allclose(renumbered.displacement, plain.displacement[order.nodes], atol=1e-5)


def test_messages_name_the_meshs_nodes_and_elements(any_size):
    model = _compression(strain=0.2)
    shuffled, order = _shuffled(model, seed=3)
    node = int(shuffled.loading.plates[1].slave_nodes[0])
    clash = Constraint(np.array([node]), np.array([[True, True, True]]), np.array([[0.0, 0.0, 1.0]]))
    clashing = Model(shuffled.mesh, shuffled.materials,
                     Loading(shuffled.loading.constraints + [Constraint.fixed([node]), clash]))
    with pytest.raises(ValueError, match=rf"nodes \[{node}\] are given different prescribed values"):
        solve(clashing, device="cpu")
    # a plate driven through the block (110 % of its side) inverts elements: the one named is the
    # shuffled mesh's element, inverted in the configuration returned
    # shuffled mesh's element: the solver's own (Z-order) model, solved as it is, names its element
    # e; the shuffled model, solved in that order inside, names order.elements[e]
    shuffled, _ = _shuffled(_compression(strain=1.1, formulation="T4"), seed=3)
    inside = SolverOrder.for_mesh(shuffled.mesh)
    assert SolverOrder.for_mesh(inside.model(shuffled).mesh) is None

    def first_element(model):
        s = solve(model, device="cpu")
        assert s.status == "inverted elements", s.message
        return int(s.message.split("first element ")[1].split(";")[0])

    assert first_element(shuffled) == inside.elements[first_element(inside.model(shuffled))]
