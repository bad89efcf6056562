"""Coulomb friction on rigid plates (kernels.touch_plate's return mapping), on warp's CPU device:
the stick limit equals fully prescribed contact faces, a sliding plate drags the tissue with mu
times its normal force, dynamic relaxation follows the physical-time path on a TetGen breast, a
batch with a friction coefficient per model equals separate solves, bad coefficients are refused."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import (Constraint, DynamicRelaxation, ElementMaterials, Loading, Material, Model, Plate,
                                     solve, solve_batch)

SIDE = 10.0  # mm
TRAVEL = 2.0  # mm


def _block():
    mesh = box_mesh((SIDE, SIDE, SIDE), (4, 4, 4))
    return mesh, np.flatnonzero(mesh.point_data["face_zlo"]), np.flatnonzero(mesh.point_data["face_zhi"])


def _model(mesh, constraints, plates):
    materials = ElementMaterials.uniform(len(mesh.tets), Material(10e3, 0.45))
    return Model(mesh, materials, Loading(constraints, plates, total_time=0.2, settle_time=0.1), damping=200.0)


@pytest.mark.parametrize("relaxed", [False, True])
def test_sticking_plates_equal_prescribed_contact_faces(relaxed):
    """A block squeezed between plates of mu = 10 (every contact node sticks: the faces cannot
    spread) deforms as the same block whose faces are prescribed: bottom fixed, top moved
    straight down. Independent of the contact code: only prescribed displacements there."""
    mesh, bottom, top = _block()
    sticking = _model(mesh, [], [Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], bottom, "bottom", friction=10.0),
                                 Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -TRAVEL], top, "top", friction=10.0)])
    prescribed = _model(mesh, [Constraint.fixed(bottom),
                               Constraint(top, np.ones((len(top), 3), bool), np.tile([0, 0, -TRAVEL], (len(top), 1)))],
                        [])
    options = {"relaxation": DynamicRelaxation(load_iterations=300)} if relaxed else {}
    stick, fixed = solve(sticking, device="cpu", **options), solve(prescribed, device="cpu", **options)
    assert stick.ok and fixed.ok, stick.message
    assert np.abs(stick.displacement - fixed.displacement).max() < 1e-4  # mm, of 2 mm travel
    # the faces bulge in the middle without friction: a different answer
    free = solve(_model(mesh, [], [Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], bottom, "bottom"),
                                   Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -TRAVEL], top, "top")]),
                 device="cpu", **options)
    assert np.abs(free.displacement - fixed.displacement)[top, :2].max() > 0.2


@pytest.mark.parametrize("relaxed", [False, True])
def test_a_sliding_plate_drags_the_tissue_with_mu_times_its_normal_force(relaxed):
    """The block's base fixed, the top plate pressed 1 mm in and slid 3 mm along x: at mu = 0.3
    the contact slips (sticking would need a shear force well above mu f_n) and the plate's
    tangential force is mu times its normal force along the slide; at mu = 0 there is none and
    the slide changes nothing."""
    mesh, bottom, top = _block()
    options = {"relaxation": DynamicRelaxation(load_iterations=300)} if relaxed else {}

    def slide(mu, along):
        plate = Plate([0, 0, SIDE], [0, 0, -1], [along, 0, -1.0], top, "top", friction=mu)
        s = solve(_model(mesh, [Constraint.fixed(bottom)], [plate]), device="cpu", **options)
        assert s.ok, s.message
        return s

    slipping = slide(0.3, 3.0)
    normal, tangential = slipping.plate_normal_forces[0], slipping.plate_tangential_forces[0]
    assert normal > 0.1  # N, pressing on the tissue
    assert tangential[0] / normal == pytest.approx(0.3, rel=0.05)
    assert np.linalg.norm(tangential) <= 0.3 * normal * (1 + 1e-4)  # never more than Coulomb's limit
    assert abs(tangential[1]) < 0.05 * tangential[0]
    assert slipping.displacement[top, 0].mean() > 1.0  # dragged along, less than the plate's 3 mm
    frictionless, still = slide(0.0, 3.0), slide(0.0, 0.0)
    np.testing.assert_array_equal(frictionless.plate_tangential_forces, 0.0)
    np.testing.assert_allclose(frictionless.displacement, still.displacement, atol=1e-9)


def _breast(mu, **options):
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression

    model = hemi_ellipsoid_compression(10.0, smooth=True, **options)
    for plate in model.loading.plates:
        plate.friction = mu
    return model


@pytest.mark.slow
def test_relaxation_follows_the_physical_time_path_with_friction_on_a_tetgen_breast():
    """Friction makes the answer depend on the path: dynamic relaxation loads over enough
    shear-wave crossings to follow the plates' monotone path, and ends within 0.1 mm of the
    settled physical-time solve at mu = 0.3 on a TetGen breast (2.5k tets); friction itself
    moves the nodes by far more than that."""
    physical = solve(_breast(0.3, total_time=1.0, settle_time=2.0), device="cpu")
    relaxed = solve(_breast(0.3), device="cpu", relaxation=DynamicRelaxation(load_iterations=300, tolerance_mm=0.005))
    frictionless = solve(_breast(0.0), device="cpu", relaxation=DynamicRelaxation(load_iterations=300,
                                                                                   tolerance_mm=0.005))
    assert physical.ok and relaxed.ok and frictionless.ok, relaxed.message
    assert np.abs(relaxed.displacement - physical.displacement).max() < 0.1
    np.testing.assert_allclose(relaxed.plate_forces, physical.plate_forces, atol=0.02 * np.abs(physical.plate_forces).max())
    assert np.abs(relaxed.displacement - frictionless.displacement).max() > 0.5
    assert np.all(np.linalg.norm(relaxed.plate_tangential_forces, axis=1) > 0.01 * relaxed.plate_normal_forces)


def test_friction_per_model_of_a_batch_equals_separate_solves():
    mesh, bottom, top = _block()
    model = _model(mesh, [Constraint.fixed(bottom)], [Plate([0, 0, SIDE], [0, 0, -1], [2.0, 0, -1.0], top, "top")])
    plate = model.loading.plates[0]
    sets = [[Plate(plate.point, plate.normal, plate.displacement, top, "top", friction=mu)] for mu in (0.0, 0.2, 0.5)]
    materials = [model.materials] * 3
    relaxation = DynamicRelaxation(load_iterations=300)
    batch = solve_batch(model, materials, device="cpu", relaxation=relaxation, plates=sets)
    for plates, together in zip(sets, batch):
        alone = solve(_model(mesh, model.loading.constraints, plates), device="cpu", relaxation=relaxation)
        assert together.ok and alone.ok
        np.testing.assert_allclose(together.displacement, alone.displacement, atol=1e-5)
        np.testing.assert_allclose(together.plate_forces, alone.plate_forces, rtol=1e-3, atol=1e-6)
    assert batch[0].displacement[top, 0].mean() < batch[1].displacement[top, 0].mean() < \
        batch[2].displacement[top, 0].mean()
    with pytest.raises(ValueError, match="contact nodes"):
        solve_batch(model, materials[:1], device="cpu", plates=[[Plate(plate.point, plate.normal, plate.displacement,
                                                                       bottom, "top")]])
    with pytest.raises(ValueError, match="either"):
        solve_batch(model, materials[:1], device="cpu", plates=sets[:1], plate_displacements=[plate.displacement])


@pytest.mark.parametrize("mu", [-0.1, float("nan"), float("inf")])
def test_bad_friction_coefficients_are_refused(mu):
    with pytest.raises(ValueError, match="friction coefficient"):
        Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], [0], "top", friction=mu)


@pytest.mark.gpu
def test_cpu_and_cuda_agree_with_friction_tilt_and_a_sliding_support():
    """Friction (stick and slip), a tilted plate and a sliding base on both devices."""
    wp = pytest.importorskip("warp")
    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device")
    from BreastBiomechLib.solver.model import SurfaceSupport
    from BreastBiomechLib.solver.placement import posed_plate
    from BreastBiomechLib.solver.supports import surface_normals_and_areas

    mesh, bottom, top = _block()
    normals, areas = surface_normals_and_areas(mesh, bottom)
    plate = posed_plate(Plate([5, 5, SIDE], [0, 0, -1], [2.0, 0, -1.0], top, "top", friction=0.3), mesh.nodes,
                        (1.0, -0.5))
    model = _model(mesh, [Constraint.fixed(bottom[:1])], [plate])
    model.loading.supports = [SurfaceSupport(bottom, normals, areas, "sliding", tangential_stiffness=50.0)]
    for options in ({}, {"relaxation": DynamicRelaxation(load_iterations=300)}):
        cpu, gpu = solve(model, device="cpu", **options), solve(model, device="cuda", **options)
        assert cpu.ok and gpu.ok, (cpu.message, gpu.message)
        np.testing.assert_allclose(gpu.displacement, cpu.displacement, atol=1e-4)
        np.testing.assert_allclose(gpu.plate_forces, cpu.plate_forces, rtol=1e-3, atol=1e-5)
