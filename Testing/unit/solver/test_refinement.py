"""A model on the uniform refinement of its mesh (solver/refinement.py, what the diagnosis's
measured floor solves): every node-based input reaches exactly the refined nodes it should, and
a homogeneous compression, which linear tetrahedra represent exactly on any mesh, gives the same
displacement at the coarse nodes (a patch test of the carried-over model)."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import (Constraint, DynamicRelaxation, ElementMaterials, Loading, Material, Model, Plate,
                                     solve)
from BreastBiomechLib.solver.model import PlateEdge, ReferenceState, SurfaceSupport
from BreastBiomechLib.solver.refinement import Refinement
from BreastBiomechLib.solver.supports import surface_normals_and_areas

SIDE = 10.0  # mm


def _quarter_block(divisions=2, strain=0.2):
    """A cube under frictionless plates at z = 0 (fixed) and z = SIDE (down by strain * SIDE),
    symmetry planes x = 0 and y = 0, two materials (by x) and a tissue array."""
    mesh = box_mesh((SIDE, SIDE, SIDE), (divisions,) * 3)
    bottom, top = (np.flatnonzero(mesh.point_data[f"face_z{end}"]) for end in ("lo", "hi"))
    constraints = [Constraint.fixed(np.flatnonzero(mesh.point_data["face_xlo"]), (True, False, False)),
                   Constraint.fixed(np.flatnonzero(mesh.point_data["face_ylo"]), (False, True, False))]
    plates = [Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], bottom, "fixed"),
              Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -strain * SIDE], top, "moving")]
    centroids = mesh.nodes[mesh.tets].mean(axis=1)
    mesh.cell_data["tissue"] = (centroids[:, 0] > SIDE / 2).astype(np.int32)
    materials = ElementMaterials.uniform(len(mesh.tets), Material(10e3, 0.45))
    return Model(mesh, materials, Loading(constraints, plates, total_time=0.2, settle_time=0.1), damping=200.0)


def test_every_node_set_reaches_the_refined_nodes_it_should():
    """On a cube the sets are faces: a refined node is in a face's set exactly where it lies on that
    face (midpoints of face edges, not of chords through the volume); prescribed components and
    values carry over; each element's materials and cell data reach its eight children; a surface
    support gets the refined surface's normals and areas; a reference state's displacement is
    interpolated at the midpoints."""
    model = _quarter_block()
    values = np.zeros((len(model.loading.constraints[0].nodes), 3))
    values[:, 0] = 0.5 * model.mesh.nodes[model.loading.constraints[0].nodes, 2]  # x shift growing with z
    model.loading.constraints[0] = Constraint(model.loading.constraints[0].nodes, (True, False, False), values)
    support_nodes = np.flatnonzero(model.mesh.point_data["face_xhi"])
    normals, areas = surface_normals_and_areas(model.mesh, support_nodes)
    model.loading.supports = [SurfaceSupport(support_nodes, normals, areas)]
    model.prestate = ReferenceState(0.01 * model.mesh.nodes * [1.0, 1.0, 0.0], [0.0, 0.0, -9.81])  # plates untouched
    mu = np.where(model.mesh.cell_data["tissue"] == 1, 3.0, 1.0) * model.materials.mu
    model.materials = ElementMaterials(mu, model.materials.kappa, model.materials.eta, model.materials.fibre,
                                       model.materials.density)
    refinement = Refinement(model.mesh)
    refined = refinement.model(model)
    nodes = refined.mesh.nodes
    assert len(refined.mesh.tets) == 8 * len(model.mesh.tets)
    np.testing.assert_array_equal(nodes[:len(model.mesh.nodes)], model.mesh.nodes)

    def on(axis, value):
        return set(np.flatnonzero(np.isclose(nodes[:, axis], value)).tolist())

    x_sym, y_sym = refined.loading.constraints
    assert set(x_sym.nodes.tolist()) == on(0, 0.0) and set(y_sym.nodes.tolist()) == on(1, 0.0)
    assert np.all(x_sym.mask == [True, False, False]) and np.all(y_sym.mask == [False, True, False])
    np.testing.assert_allclose(x_sym.values[:, 0], 0.5 * nodes[x_sym.nodes, 2])  # linear: exact at midpoints
    bottom, top = refined.loading.plates
    assert set(bottom.slave_nodes.tolist()) == on(2, 0.0) and set(top.slave_nodes.tolist()) == on(2, SIDE)
    [support] = refined.loading.supports
    assert set(support.nodes.tolist()) == on(0, SIDE)
    np.testing.assert_allclose(support.normals, np.tile([1.0, 0.0, 0.0], (len(support.nodes), 1)), atol=1e-12)
    assert support.areas.sum() == pytest.approx(SIDE * SIDE)
    np.testing.assert_allclose(refined.prestate.displacement, 0.01 * nodes * [1.0, 1.0, 0.0])
    parents = np.arange(len(refined.mesh.tets)) // 8
    np.testing.assert_array_equal(refined.materials.mu, model.materials.mu[parents])
    np.testing.assert_array_equal(refined.mesh.cell_data["tissue"], model.mesh.cell_data["tissue"][parents])
    assert refined.time_step is None and refined.formulation == model.formulation


def test_a_midpoint_that_starts_behind_a_rounded_plate_edge_is_not_among_its_contact_nodes():
    """A rounded plate edge is convex: the chord between two top nodes clear of it, one on its flat
    face and one lifted onto its fillet, passes behind it (found by the design's floor on a case
    whose plates the plate tilt had turned: "plate 'left' cuts into the tissue at the start").
    That midpoint is left out of the refined plate's contact nodes, and the refined model is
    built; every coarse contact node and the other midpoints stay."""
    from dataclasses import replace

    model = _quarter_block()
    on_top = np.isclose(model.mesh.nodes[:, 2], SIDE)
    far = on_top & np.isclose(model.mesh.nodes[:, 0], SIDE)
    model.mesh.nodes[far, 2] = SIDE + 1.3  # on the fillet below, 0.03 mm clear of it
    top = replace(model.loading.plates[1], edge=PlateEdge([1.0, 0.0, 0.0], SIDE / 2, 10.0))
    model.loading.plates[1] = top
    assert top.gaps(model.mesh.nodes[top.slave_nodes]).min() >= 0  # the coarse model is clear
    refinement = Refinement(model.mesh)
    refined = refinement.model(model)
    kept = refined.loading.plates[1].slave_nodes
    candidates = refinement.nodes_of(top.slave_nodes)[0]
    behind = candidates[top.gaps(refined.mesh.nodes[candidates]) < -1e-3]
    assert len(behind) and set(behind.tolist()).isdisjoint(kept.tolist())
    assert (behind >= len(model.mesh.nodes)).all()  # midpoints of chords from x = SIDE / 2 to SIDE
    assert set(kept.tolist()) == set(candidates.tolist()) - set(behind.tolist())
    assert top.gaps(refined.mesh.nodes[kept]).min() > -1e-3


def test_a_homogeneous_compression_is_the_same_on_the_refined_mesh():
    """Patch test of the carried-over model: uniaxial compression of one material between
    frictionless plates is a uniform strain, which both meshes represent exactly, so the refined
    solution at the coarse nodes is the coarse one (within the relaxation's tolerance)."""
    model = _quarter_block()
    relaxation = DynamicRelaxation(load_iterations=300, tolerance_mm=0.001)
    coarse = solve(model, device="cpu", relaxation=relaxation)
    fine = solve(Refinement(model.mesh).model(model), device="cpu", relaxation=relaxation)
    assert coarse.ok and fine.ok, (coarse.message, fine.message)
    np.testing.assert_allclose(fine.displacement[:len(model.mesh.nodes)], coarse.displacement, atol=0.01)
    assert np.abs(coarse.displacement[:, 2]).max() == pytest.approx(0.2 * SIDE, rel=1e-3)
