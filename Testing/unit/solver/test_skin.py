"""A skin layer on meshes coarser than the skin (mesh.skin, ElementMaterials.with_skin, case files'
``skin``): exact layer shares on a block, Voigt weighting, the layer's effect on a TetGen breast
under refinement, the mesh's own skin elements, refusals."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.mesh.skin import skin_fraction, surface_distance
from BreastBiomechLib.solver import ElementMaterials, Material


def _block():
    mesh = box_mesh((10.0, 10.0, 10.0), (4, 4, 4))  # layers 2.5 mm thick
    return mesh, np.flatnonzero(mesh.point_data["face_zhi"])


def test_layer_shares_on_a_block():
    mesh, top = _block()
    np.testing.assert_allclose(surface_distance(mesh, top), 10.0 - mesh.nodes[:, 2], atol=1e-9)
    depth = 10.0 - mesh.nodes[mesh.tets].min(axis=1)[:, 2]  # the deepest node of each element
    whole = skin_fraction(mesh, top, 2.5)  # exactly the top layer of elements
    np.testing.assert_array_equal(whole, np.where(depth <= 2.5 + 1e-9, 1.0, 0.0))
    half = skin_fraction(mesh, top, 1.25)  # half of it: the layer's volume, whatever the split
    assert half @ mesh.volumes == pytest.approx(100.0 * 1.25, rel=0.02)
    assert np.all((half > 0) == (whole > 0))


def test_voigt_weighting_of_the_skin():
    base = ElementMaterials.uniform(3, Material(10e3, 0.45, eta=2e3))
    skin = Material(50e3, 0.49)
    mixed = base.with_skin([0.0, 0.5, 1.0], skin)
    np.testing.assert_allclose(mixed.mu, [base.mu[0], 0.5 * (base.mu[0] + skin.mu), skin.mu])
    np.testing.assert_allclose(mixed.kappa, [base.kappa[0], 0.5 * (base.kappa[0] + skin.kappa), skin.kappa])
    np.testing.assert_allclose(mixed.eta, [2e3, 1e3, 0.0])
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        base.with_skin([0.0, 1.5, 0.0], skin)


@pytest.mark.slow
def test_the_skin_effect_on_a_tetgen_breast_settles_under_refinement():
    """A 2 mm skin of 50 kPa on a 3 kPa TetGen breast compressed 25 %: the layer's volume is the
    same on 10, 7 and 5 mm meshes (within 3 %), and the plate force it adds is positive and falls
    as the mesh is refined (the Voigt weighting is an upper bound: a coarse element that holds
    the layer stiffens more tissue than the layer is): +32 %, +29 %, +24 % here, converging to
    +18 % at 2.5-1.6 mm (H100 run in docs/solver.md)."""
    from dataclasses import replace

    from BreastBiomechLib.solver import DynamicRelaxation, solve
    from BreastBiomechLib.solver.cases import hemi_ellipsoid_compression

    layers, effects = [], []
    for spacing in (10.0, 7.0, 5.0):
        model = hemi_ellipsoid_compression(spacing, material=Material(3e3, 0.49), smooth=True)
        pd = model.mesh.point_data
        skin = np.flatnonzero(pd["surface"].astype(bool) & ~pd["chest_wall"].astype(bool))
        fraction = skin_fraction(model.mesh, skin, 2.0)
        layers.append(fraction @ model.mesh.volumes)
        plain = solve(model, device="cpu", relaxation=DynamicRelaxation())
        skinned = solve(replace(model, materials=model.materials.with_skin(fraction, Material(50e3, 0.49))),
                        device="cpu", relaxation=DynamicRelaxation())
        assert plain.ok and skinned.ok
        effects.append(skinned.plate_normal_forces[0] / plain.plate_normal_forces[0] - 1.0)
    assert max(layers) / min(layers) < 1.03
    assert effects[0] > effects[1] > effects[2] > 0.1


def test_case_files_carry_a_skin_layer(tmp_path):
    from BreastBiomechLib.io.cases import read_case
    from BreastBiomechLib.io.meshes import write_vtu

    mesh, top = _block()
    write_vtu(tmp_path / "block.vtu", mesh)

    def case(skin):
        (tmp_path / "case.json").write_text(json.dumps({"mesh": "block.vtu", "materials": {"default": {"E": 1e4, "nu": 0.45}},
                                                        "skin": skin}))
        return read_case(tmp_path / "case.json")[0]

    model = case({"E": 5e4, "nu": 0.45, "thickness_mm": 2.5, "nodes": top.tolist()})
    expected = ElementMaterials.uniform(len(mesh.tets), Material(1e4, 0.45)).with_skin(
        skin_fraction(mesh, top, 2.5), Material(5e4, 0.45))
    np.testing.assert_allclose(model.materials.mu, expected.mu)
    # the layer is 0.25 cm^3: whether it prints as 0.2 or 0.3 is the platform's last-bit rounding
    assert re.search(r"partial-volume weighting of 96 elements \(0\.[23] cm\^3 of layer\)", model.loading.notes[0])
    for bad, match in (({"E": 5e4, "nu": 0.45}, "skin is"), ({"E": 5e4, "nu": 0.45, "thickness_mm": -1}, "positive"),
                       ({"E": 5e4, "nu": 0.45, "thickness_mm": 12, "nodes": top.tolist()}, "as thick as the breast"),
                       ({"E": "stiff", "nu": 0.45, "thickness_mm": 2}, "skin E must be a number")):
        with pytest.raises(ValueError, match=match) as error:
            case(bad)
        assert "case.json" in str(error.value)


def test_skin_elements_of_the_mesh_take_the_skin_material(tmp_path):
    from BreastBiomechLib.io.cases import case_from_dict
    from BreastBiomechLib.labels import FAT, SKIN

    mesh, top = _block()
    tissue = np.where(mesh.nodes[mesh.tets].mean(axis=1)[:, 2] > 7.5, SKIN.label, FAT.label).astype(np.int32)
    mesh.cell_data["tissue"] = tissue
    model, _ = case_from_dict({"materials": {"fat": {"E": 1e4, "nu": 0.45}, "skin": {"E": 2e4, "nu": 0.45}},
                               "skin": {"E": 5e4, "nu": 0.45, "thickness_mm": 2.0}}, mesh)
    assert np.allclose(model.materials.mu[tissue == SKIN.label], Material(5e4, 0.45).mu)
    assert np.allclose(model.materials.mu[tissue == FAT.label], Material(1e4, 0.45).mu)
    assert "the mesh's 96 skin elements" in model.loading.notes[0]
