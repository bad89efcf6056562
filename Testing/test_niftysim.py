"""NiftySim XML round trip: a model written and read back is the same model and gives the same
solution; unsupported content is refused with the reason."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from BreastBiomechLib.io.niftysim import read_niftysim, write_niftysim
from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import Constraint, ElementMaterials, Loading, Material, Model, Plate, solve

SIDE = 10.0


def _model(settle_time=0.0):
    mesh = box_mesh((SIDE, SIDE, SIDE), (3, 3, 3))
    upper = mesh.nodes[mesh.tets].mean(axis=1)[:, 2] > SIDE / 2
    materials = ElementMaterials.from_tissues(upper.astype(int) + 1, {
        1: Material(10e3, 0.45, prony=((0.3, 0.05),)),
        2: Material(20e3, 0.47, eta=2e3, fibre=(0.6, 0.0, 0.8), density=1050.0)})
    pd = mesh.point_data
    top = np.flatnonzero(pd["face_zhi"])
    pulled = top[(pd["face_xlo"][top] == 0) & (pd["face_ylo"][top] == 0)][:3]
    loading = Loading([Constraint.fixed(np.flatnonzero(pd["face_xlo"]), (True, False, False)),
                       Constraint.fixed(np.flatnonzero(pd["face_ylo"]), (False, True, False)),
                       Constraint(pulled, [[True, False, False]] * 3, [[0.2, 0, 0]] * 3)],
                      [Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], np.flatnonzero(pd["face_zlo"]), "base"),
                       Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -2.0], top, "top")],
                      gravity=[0, 0, -9.81], total_time=0.2, settle_time=settle_time)
    return Model(mesh, materials, loading, damping=200.0, formulation="T4ANP")


def test_round_trip_keeps_the_model_and_its_solution(tmp_path):
    model = _model()
    path = write_niftysim(tmp_path / "block.xml", model)
    root = ET.parse(path).getroot()
    assert root.find("Elements").get("Type") == "T4ANP"
    assert sorted(m.get("Type") for m in root.iter("Material")) == ["NHV", "TI"]
    assert len(root.findall("ContactPlate")) == 2
    back = read_niftysim(path)
    np.testing.assert_allclose(back.mesh.nodes, model.mesh.nodes, atol=1e-9)
    np.testing.assert_array_equal(back.mesh.tets, model.mesh.tets)
    for name in ("mu", "kappa", "eta", "fibre", "density", "prony_g", "prony_tau"):
        np.testing.assert_allclose(getattr(back.materials, name), getattr(model.materials, name), rtol=1e-8)
    np.testing.assert_allclose(back.loading.gravity, model.loading.gravity)
    for p, q in zip(back.loading.plates, model.loading.plates):
        np.testing.assert_allclose(p.normal, q.normal, atol=1e-12)
        assert abs(np.dot(p.point - q.point, q.normal)) < 1e-9  # same plane
        np.testing.assert_allclose(p.displacement, q.displacement, atol=1e-12)
        np.testing.assert_array_equal(p.slave_nodes, q.slave_nodes)
    a, b = solve(model, device="cpu"), solve(back, device="cpu")
    assert a.ok and b.ok
    np.testing.assert_allclose(b.displacement, a.displacement, atol=1e-5)


def test_settling_and_unsupported_content_are_refused(tmp_path):
    with pytest.raises(ValueError, match="no settling phase"):
        write_niftysim(tmp_path / "m.xml", _model(settle_time=0.1))
    write_niftysim(tmp_path / "m.xml", _model(settle_time=0.1), drop_settling=True)
    text = (tmp_path / "m.xml").read_text().replace('Type="TI"', 'Type="AB"')
    (tmp_path / "ab.xml").write_text(text)
    with pytest.raises(ValueError, match="material type 'AB'"):
        read_niftysim(tmp_path / "ab.xml")
    (tmp_path / "broken.xml").write_text("<Model><Nodes>")
    with pytest.raises(ValueError, match="not valid XML"):
        read_niftysim(tmp_path / "broken.xml")
