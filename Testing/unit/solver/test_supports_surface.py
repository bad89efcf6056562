"""Chest-wall support modes (solver.supports.chest_wall_support, kernels.advance_nodes and
support_springs) on warp's CPU device: a sliding base equals a frictionless plate, an elastic base
compresses as springs in series with the block, a sliding chest wall keeps zero normal
displacement and changes the breast's answer, rigid motion is stopped or the set-up refused."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import (Constraint, DynamicRelaxation, ElementMaterials, Loading, Material, Model, Plate,
                                     solve)
from BreastBiomechLib.solver.model import SurfaceSupport
from BreastBiomechLib.solver.supports import chest_wall_support, surface_normals_and_areas

SIDE = 10.0
E = 10e3


def _quarter_block(bottom_support, top_travel=2.0):
    """Quarter block on symmetry planes x = 0, y = 0, pressed by a frictionless top plate."""
    mesh = box_mesh((SIDE, SIDE, SIDE), (4, 4, 4))
    face = {name: np.flatnonzero(mesh.point_data[f"face_{name}"]) for name in ("xlo", "ylo", "zlo", "zhi")}
    constraints = [Constraint.fixed(face["xlo"], (True, False, False)),
                   Constraint.fixed(face["ylo"], (False, True, False))]
    plates = [Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -top_travel], face["zhi"], "top")]
    supports = []
    if bottom_support == "plate":
        plates.append(Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], face["zlo"], "bottom"))
    else:
        normals, areas = surface_normals_and_areas(mesh, face["zlo"])
        supports.append(SurfaceSupport(face["zlo"], normals, areas, *bottom_support))
    loading = Loading(constraints, plates, total_time=0.2, settle_time=0.1, supports=supports)
    return mesh, face, Model(mesh, ElementMaterials.uniform(len(mesh.tets), Material(E, 0.45)), loading, damping=200.0)


def test_surface_normals_and_areas_of_a_face():
    mesh = box_mesh((SIDE, SIDE, SIDE), (4, 4, 4))
    bottom = np.flatnonzero(mesh.point_data["face_zlo"])
    normals, areas = surface_normals_and_areas(mesh, bottom)
    np.testing.assert_allclose(normals, np.tile([0, 0, -1.0], (len(bottom), 1)), atol=1e-12)
    assert areas.sum() == pytest.approx(SIDE * SIDE)


@pytest.mark.parametrize("relaxed", [False, True])
def test_a_sliding_base_equals_a_frictionless_plate(relaxed):
    options = {"relaxation": DynamicRelaxation(load_iterations=300)} if relaxed else {}
    *_, on_plate = _quarter_block("plate")
    mesh, face, sliding = _quarter_block(("sliding",))
    a, b = solve(on_plate, device="cpu", **options), solve(sliding, device="cpu", **options)
    assert a.ok and b.ok, b.message
    np.testing.assert_allclose(b.displacement, a.displacement, atol=2e-5)
    np.testing.assert_allclose(b.displacement[face["zlo"], 2], 0.0, atol=1e-7)


def test_an_elastic_base_compresses_as_springs_in_series_with_the_block():
    """Top pressed 0.1 mm (small strain): the base springs (k per area) carry the block's stress
    sigma = k u_b = E (delta - u_b) / h, so u_b = E delta / (k h + E): half the travel at
    k = E / h. A tangential stiffness a thousand times smaller stops rigid motion unnoticed."""
    k = E / SIDE  # Pa/mm
    mesh, face, model = _quarter_block(("elastic", k, k * 1e-3), top_travel=0.1)
    s = solve(model, device="cpu", relaxation=DynamicRelaxation(load_iterations=300, tolerance_mm=1e-5))
    assert s.ok, s.message
    sink = -s.displacement[face["zlo"], 2]
    assert sink.mean() == pytest.approx(0.05, rel=0.02)
    assert np.ptp(sink) < 0.05 * sink.mean()
    stiffer = solve(_quarter_block(("elastic", 9 * k, k * 1e-3), top_travel=0.1)[2], device="cpu",
                    relaxation=DynamicRelaxation(load_iterations=300, tolerance_mm=1e-5))
    assert -stiffer.displacement[face["zlo"], 2].mean() == pytest.approx(0.01, rel=0.02)


def test_a_sliding_chest_wall_keeps_zero_normal_displacement_and_changes_the_answer():
    """On the hemi-ellipsoid's flat chest wall (y = 0) sliding along the local normal is the
    seed's condition (fixed in y, anchor patches): the same answer by another kernel. A fully
    fixed chest wall is a different one."""
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression

    seed = hemi_ellipsoid_compression(10.0)
    mesh = seed.mesh
    chest = np.flatnonzero(mesh.point_data["chest_wall"])

    def with_support(kind, **options):
        constraints, supports, sentence = chest_wall_support(mesh, chest, kind, **options)
        loading = Loading(constraints, seed.loading.plates, total_time=1.0, supports=supports)
        return Model(mesh, seed.materials, loading, damping=seed.damping), supports, sentence

    sliding, supports, sentence = with_support("sliding")
    assert "sliding" in sentence and "rigid motion along it stopped by fixing" in sentence
    fixed, _, fixed_sentence = with_support("fixed", components=(True, True, True))
    assert fixed_sentence.startswith("chest wall fixed in xyz")
    relaxation = DynamicRelaxation(load_iterations=300)
    a, b, c = (solve(m, device="cpu", relaxation=relaxation) for m in (seed, sliding, fixed))
    assert a.ok and b.ok and c.ok, b.message
    along_normal = np.einsum("ij,ij->i", b.displacement[chest], supports[0].normals)
    assert np.abs(along_normal).max() < 1e-6
    assert np.linalg.norm(b.displacement[chest], axis=1).max() > 1.0  # the chest wall nodes slide
    np.testing.assert_allclose(b.displacement, a.displacement, atol=1e-3)
    assert np.abs(c.displacement - b.displacement).max() > 1.0
    np.testing.assert_array_equal(c.displacement[chest], 0.0)


def test_supports_that_leave_rigid_motion_free_or_bad_values_are_refused():
    mesh = box_mesh((SIDE, SIDE, SIDE), (2, 2, 2))
    bottom = np.flatnonzero(mesh.point_data["face_zlo"])
    with pytest.raises(ValueError, match="free to slide and turn"):
        chest_wall_support(mesh, bottom, "sliding", anchor=False)
    constraints, supports, sentence = chest_wall_support(mesh, bottom, "elastic", normal_stiffness=5.0,
                                                         tangential_stiffness=1.0, anchor=False)
    assert constraints == [] and "tangential springs stop rigid motion" in sentence
    with pytest.raises(ValueError, match="normal stiffness > 0"):
        chest_wall_support(mesh, bottom, "elastic")
    with pytest.raises(ValueError, match="one of"):
        chest_wall_support(mesh, bottom, "glued")
    with pytest.raises(ValueError, match="finite number >= 0"):
        chest_wall_support(mesh, bottom, "sliding", tangential_stiffness=-1.0)
    interior = np.flatnonzero(np.all(np.abs(mesh.nodes - SIDE / 2) < 1e-9, axis=1))
    with pytest.raises(ValueError, match="lie on no boundary face"):
        surface_normals_and_areas(mesh, interior)


def test_case_files_carry_chest_wall_supports(tmp_path):
    import json

    from BreastBiomechLib.io.cases import read_case
    from BreastBiomechLib.io.meshes import write_vtu

    mesh = box_mesh((4 * SIDE, 4 * SIDE, SIDE), (4, 4, 1))  # wide enough for the anchor patches
    write_vtu(tmp_path / "block.vtu", mesh)
    bottom = np.flatnonzero(mesh.point_data["face_zlo"]).tolist()

    def case(**support):
        path = tmp_path / "case.json"
        path.write_text(json.dumps({"mesh": "block.vtu", "materials": {"default": {"E": 1e4, "nu": 0.45}},
                                    "supports": [{"nodes": bottom, **support}]}))
        return read_case(path)[0]

    sliding = case(kind="sliding")
    assert sliding.loading.supports[0].mode == "sliding" and "sliding" in sliding.loading.notes[0]
    assert len(sliding.loading.constraints) == 2  # the anchor patches
    elastic = case(kind="elastic", normal_stiffness=3.0, tangential_stiffness=0.5)
    assert elastic.loading.supports[0].tangential_stiffness == 0.5 and elastic.loading.constraints == []
    fixed = case(kind="fixed", components="z", anchor=False)
    assert fixed.loading.supports == [] and fixed.loading.constraints[0].mask[:, 2].all()
    for bad, match in (({"kind": "glued"}, "support 0: the chest-wall support is one of"),
                       ({"kind": "elastic"}, "normal stiffness > 0"), ({"stiffness": 1}, "unknown fields"),
                       ({"kind": "sliding", "tangential_stiffness": "firm"}, "must be a number"),
                       ({"anchor": "yes"}, "anchor must be true or false")):
        with pytest.raises(ValueError, match=match) as error:
            case(**bad)
        assert "case.json" in str(error.value)
