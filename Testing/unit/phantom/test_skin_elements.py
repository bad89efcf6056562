"""A phantom truth's skin as explicit elements (phantom.skin_elements), made apart from the
discrepancy workflow's skin candidate (issue 77, point 5)."""

from __future__ import annotations

import numpy as np
import pytest


def _ball(radius_mm=30.0, edge_mm=2.5):
    """A half ball meshed by TetGen, all fat; its skin the curved surface (the flat side is the
    chest wall)."""
    from BreastBiomechLib.labels import FAT
    from BreastBiomechLib.mesh.primitives import smooth_hemi_ellipsoid_mesh
    from BreastBiomechLib.mesh.tetmesh import TetMesh

    mesh = smooth_hemi_ellipsoid_mesh((radius_mm,) * 3, edge_mm)
    skin = (mesh.point_data["surface"] > 0) & (mesh.nodes[:, 1] < -1e-6)
    return TetMesh(mesh.nodes, mesh.tets, {**mesh.point_data, "skin": skin.astype(np.uint8)},
                   {"tissue": np.full(len(mesh.tets), FAT.label, np.int32)})


def test_the_truth_skin_is_the_elements_within_its_thickness_of_the_skin():
    """On a half ball of radius R the depth of an element's centroid below the skin is R - |c| (the
    faceted surface within a hundredth of a millimetre): the elements labelled skin are those
    nearer than the thickness (every one clear of the threshold by 0.2 mm agrees), muscle stays
    muscle, the layer's thickness as the elements hold it is near the thickness asked for, and a
    skin thinner than any element's centroid depth is refused, naming the remedy."""
    from BreastBiomechLib.labels import FAT, MUSCLE, SKIN
    from BreastBiomechLib.mesh.tetmesh import TetMesh
    from BreastBiomechLib.phantom.skin_elements import skin_layer_figures, skin_surface_edge_mm, with_skin_elements

    radius, thickness = 30.0, 4.0
    mesh = _ball(radius)
    centroids = mesh.nodes[mesh.tets].mean(axis=1)
    depth = radius - np.linalg.norm(centroids, axis=1)
    far_from_chest = centroids[:, 1] < -thickness - 3.0
    tissue = mesh.cell_data["tissue"].copy()
    muscle = far_from_chest & (centroids[:, 0] > 20.0) & (depth < 2.0)
    tissue[muscle] = MUSCLE.label
    mesh = TetMesh(mesh.nodes, mesh.tets, mesh.point_data, {"tissue": tissue})

    skinned = with_skin_elements(mesh, thickness).cell_data["tissue"]
    clear = far_from_chest & (np.abs(depth - thickness) > 0.2) & ~muscle
    np.testing.assert_array_equal(skinned[clear] == SKIN.label, depth[clear] < thickness)
    assert np.all(skinned[muscle] == MUSCLE.label) and muscle.any()
    assert set(np.unique(skinned)) == {FAT.label, MUSCLE.label, SKIN.label}
    figures = skin_layer_figures(TetMesh(mesh.nodes, mesh.tets, mesh.point_data, {"tissue": skinned}))
    assert figures["elements"] == int((skinned == SKIN.label).sum())
    assert 0.7 * thickness < figures["effective_thickness_mm"] < 1.3 * thickness
    with pytest.raises(ValueError, match="too coarse for this skin"):
        with_skin_elements(mesh, 0.01)
    with pytest.raises(ValueError, match="positive number of millimetres"):
        with_skin_elements(mesh, -1.0)
    # the truth mesh's skin triangles: thinner than the skin, never finer than 1 mm nor coarser than the mesh
    assert [skin_surface_edge_mm(3.0, t) for t in (1.0, 2.1, 3.0, 6.0)] == pytest.approx([1.0, 1.4, 2.0, 3.0])


def test_a_truth_with_a_skin_solves_it_as_elements_of_the_skin_modulus(compressed_case_dir):
    """truth_case on a phantom's truth mesh: the elements the skin takes carry the truth skin's E
    (mu = E / 2 (1 + nu)), the others their tissue's, the truth mesh's own labels untouched."""
    from BreastBiomechLib.io.meshes import read_vtu
    from BreastBiomechLib.labels import FAT, SKIN
    from BreastBiomechLib.mesh.tetmesh import TetMesh
    from BreastBiomechLib.phantom.compressed import TruthModel, truth_case
    from BreastBiomechLib.phantom.truth_files import truth_mesh_path

    made = read_vtu(truth_mesh_path(compressed_case_dir))
    tissue = made.cell_data["tissue"].copy()
    tissue[tissue == SKIN.label] = FAT.label  # a phantom made with its skin apart: start from none
    mesh = TetMesh(made.nodes, made.tets, {k: v for k, v in made.point_data.items() if k != "displacement"},
                   {**made.cell_data, "tissue": tissue})
    plain, _ = truth_case(mesh, TruthModel(compression=0.25, edge_mm=6.0))
    model, _ = truth_case(mesh, TruthModel(compression=0.25, edge_mm=6.0, skin=[77e3, 4.0]))
    layer = model.mesh.cell_data["tissue"] == SKIN.label
    assert layer.any() and not np.any(mesh.cell_data["tissue"] == SKIN.label)
    np.testing.assert_allclose(model.materials.mu[layer], 77e3 / (2 * 1.495))
    np.testing.assert_allclose(model.materials.mu[~layer], plain.materials.mu[~layer])
