"""Property-based round trips of the file formats and frame conversions (hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from BreastBiomechLib.io.markups import read_markups, write_markups
from BreastBiomechLib.io.meshes import read_vtu, write_vtu
from BreastBiomechLib.landmarks import Landmarks
from BreastBiomechLib.mesh import TetMesh

coordinates = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)
labels = st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs", "Cc")), min_size=1, max_size=12)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(coordinates, coordinates, coordinates, labels), min_size=1, max_size=20,
                unique_by=lambda t: t[3]))
def test_mrk_json_round_trip(tmp_path_factory, points):
    landmarks = Landmarks(np.array([p[:3] for p in points]), [p[3] for p in points])
    path = write_markups(tmp_path_factory.mktemp("m") / "points.mrk.json", landmarks)
    back = read_markups(path)
    np.testing.assert_array_equal(back.positions, landmarks.positions)
    assert back.labels == landmarks.labels


def test_mrk_json_errors_name_the_problem(tmp_path):
    with pytest.raises(ValueError, match="mrk.json"):
        write_markups(tmp_path / "points.json", Landmarks(np.zeros((1, 3)), ["a"]))
    bad = tmp_path / "bad.mrk.json"
    bad.write_text("{}")
    with pytest.raises(ValueError, match="not a Slicer markups"):
        read_markups(bad)
    with pytest.raises(ValueError, match="unique"):
        Landmarks(np.zeros((2, 3)), ["a", "a"])


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=1, max_value=30), st.integers(min_value=0, max_value=2**31 - 1))
def test_vtu_round_trip(tmp_path_factory, n_tets, seed):
    rng = np.random.default_rng(seed)  # a valid mesh to simulate: distinct, positive tets using every node
    nodes = rng.normal(size=(4 * n_tets, 3)) * 50
    tets = rng.permutation(len(nodes)).reshape(n_tets, 4)
    tets[TetMesh(nodes, tets).volumes < 0, :2] = tets[TetMesh(nodes, tets).volumes < 0, 1::-1]
    mesh = TetMesh(nodes, tets, point_data={"chest_wall": rng.integers(0, 2, len(nodes)).astype(np.uint8)},
                   cell_data={"tissue": rng.integers(1, 5, n_tets).astype(np.uint8),
                              "fibre_direction": rng.normal(size=(n_tets, 3))})
    back = read_vtu(write_vtu(tmp_path_factory.mktemp("v") / "mesh.vtu", mesh))
    np.testing.assert_array_equal(back.nodes, mesh.nodes)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    for name in ("tissue", "fibre_direction"):
        np.testing.assert_array_equal(back.cell_data[name], mesh.cell_data[name])
    np.testing.assert_array_equal(back.point_data["chest_wall"], mesh.point_data["chest_wall"])


def test_tetmesh_rejects_bad_connectivity():
    with pytest.raises(ValueError, match="outside"):
        TetMesh(np.zeros((3, 3)), [[0, 1, 2, 3]])
    with pytest.raises(ValueError, match="rows"):
        TetMesh(np.zeros((4, 3)), [[0, 1, 2, 3]], cell_data={"tissue": np.zeros(2)})


@pytest.mark.mrml
@settings(max_examples=30, deadline=None)
@given(st.integers(min_value=0, max_value=2**31 - 1))
def test_volume_node_geometry_round_trip_for_any_rotation(seed):
    slicer = pytest.importorskip("slicer")
    from BreastBiomechLib import mrml

    rng = np.random.default_rng(seed)
    direction = Rotation.random(random_state=seed).as_matrix()
    if rng.random() < 0.3:  # also improper (mirrored) directions, as some scanners write
        direction[:, 0] *= -1
    image = sitk.GetImageFromArray(rng.normal(size=(3, 4, 5)).astype(np.float32))
    image.SetOrigin(tuple(rng.uniform(-300, 300, 3)))
    image.SetSpacing(tuple(rng.uniform(0.2, 5.0, 3)))
    image.SetDirection(tuple(direction.ravel()))
    scene = slicer.vtkMRMLScene()
    back = mrml.image_from_volume_node(mrml.image_to_volume_node(image, scene, display=False))
    np.testing.assert_allclose(back.GetOrigin(), image.GetOrigin(), atol=1e-9)
    np.testing.assert_allclose(back.GetSpacing(), image.GetSpacing(), rtol=1e-12)
    np.testing.assert_allclose(back.GetDirection(), image.GetDirection(), atol=1e-12)
    index = tuple(int(i) for i in rng.integers(0, 3, 3))
    np.testing.assert_allclose(back.TransformIndexToPhysicalPoint(index),
                               image.TransformIndexToPhysicalPoint(index), atol=1e-9)
