"""Case files (CASE.json + .vtu) and ``breastbiomech simulate``: the file route gives the same
answer as building the model in Python, and bad cases are refused with the reason."""

from __future__ import annotations

import json

import numpy as np
import pytest

from BreastBiomechLib.cli import main
from BreastBiomechLib.io.cases import read_case
from BreastBiomechLib.io.meshes import read_vtu, write_vtu
from BreastBiomechLib.labels import FAT, GLANDULAR
from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import Constraint, ElementMaterials, Loading, Material, Model, Plate, solve

SIDE = 10.0


def _case(tmp_path, **changes):
    mesh = box_mesh((SIDE, SIDE, SIDE), (3, 3, 3))
    tissue = np.where(mesh.nodes[mesh.tets].mean(axis=1)[:, 2] < SIDE / 2, FAT.label, GLANDULAR.label)
    mesh.cell_data["tissue"] = tissue.astype(np.int32)
    write_vtu(tmp_path / "block.vtu", mesh)
    case = {
        "mesh": "block.vtu",
        "materials": {"fat": {"E": 10e3, "nu": 0.45}, "glandular": {"E": 20e3, "nu": 0.45, "eta": 2e3,
                                                                  "fibre": [1, 0, 0]}},
        "constraints": [{"nodes": "face_xlo", "components": "x"}, {"nodes": "face_ylo", "components": [0, 1, 0]}],
        "plates": [{"name": "base", "point": [0, 0, 0], "normal": [0, 0, 1], "slaves": "face_zlo"},
                   {"name": "top", "point": [0, 0, SIDE], "normal": [0, 0, -1], "displacement": [0, 0, -2.0],
                    "slaves": "face_zhi"}],
        "total_time": 0.2, "settle_time": 0.1, "damping": 200.0,
        "solver": {"method": "physical", "device": "cpu"},
    }
    case.update(changes)
    path = tmp_path / "case.json"
    path.write_text(json.dumps(case))
    return path, mesh, tissue


def test_simulate_writes_the_same_solution_as_the_library(tmp_path):
    path, mesh, tissue = _case(tmp_path)
    assert main(["simulate", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    result = read_vtu(tmp_path / "out" / "deformed.vtu")
    summary = json.loads((tmp_path / "out" / "solution.json").read_text())
    assert summary["status"] == "completed"
    np.testing.assert_array_equal(result.cell_data["tissue"], tissue)

    materials = ElementMaterials.from_tissues(tissue, {FAT.label: Material(10e3, 0.45),
                                                       GLANDULAR.label: Material(20e3, 0.45, 2e3, (1, 0, 0))})
    pd = mesh.point_data
    loading = Loading([Constraint.fixed(np.flatnonzero(pd["face_xlo"]), (True, False, False)),
                       Constraint.fixed(np.flatnonzero(pd["face_ylo"]), (False, True, False))],
                      [Plate([0, 0, 0], [0, 0, 1], [0, 0, 0], np.flatnonzero(pd["face_zlo"])),
                       Plate([0, 0, SIDE], [0, 0, -1], [0, 0, -2.0], np.flatnonzero(pd["face_zhi"]))],
                      total_time=0.2, settle_time=0.1)
    direct = solve(Model(mesh, materials, loading, damping=200.0), device="cpu")
    np.testing.assert_allclose(result.point_data["displacement"], direct.displacement, atol=1e-6)
    np.testing.assert_allclose(summary["plates"]["top"], direct.plate_forces[1], rtol=1e-5)
    # the stiffer upper half compresses less than the fat below it
    top_z = result.point_data["displacement"][pd["face_zhi"].astype(bool), 2].mean()
    assert -2.0 == pytest.approx(top_z, abs=1e-3)


def test_relaxation_is_the_default_method(tmp_path):
    path, _, _ = _case(tmp_path, solver={"device": "cpu", "tolerance_mm": 0.005})
    model, settings = read_case(path)
    assert settings.method == "relaxation" and settings.relaxation.tolerance_mm == 0.005
    assert main(["simulate", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert json.loads((tmp_path / "out" / "solution.json").read_text())["estimated_error_mm"] < 0.005


def test_static_method_gives_the_settled_physical_solution_with_and_without_mass_scaling(tmp_path):
    physical_path, _, _ = _case(tmp_path)
    (tmp_path / "static").mkdir()
    static_path, _, _ = _case(tmp_path / "static", solver={"method": "static", "increments": 2})
    assert main(["simulate", str(physical_path), "--out", str(tmp_path / "physical"), "--quiet"]) == 0
    assert main(["simulate", str(static_path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    physical = read_vtu(tmp_path / "physical" / "deformed.vtu").point_data["displacement"]
    static = read_vtu(tmp_path / "out" / "deformed.vtu").point_data["displacement"]
    summary = json.loads((tmp_path / "out" / "solution.json").read_text())
    assert summary["status"] == "completed" and "Newton" in summary["message"]
    assert np.abs(static - physical).max() < 0.01
    assert summary["history"]["load_fraction"] == [0.5, 1.0]
    (tmp_path / "scaled").mkdir()
    scaled_path, _, _ = _case(tmp_path / "scaled", solver={"method": "physical", "device": "cpu", "mass_scaling": True})
    assert main(["simulate", str(scaled_path), "--out", str(tmp_path / "scaled_out"), "--quiet"]) == 0
    scaled = read_vtu(tmp_path / "scaled_out" / "deformed.vtu").point_data["displacement"]
    assert "mass scaling" in json.loads((tmp_path / "scaled_out" / "solution.json").read_text())["message"]
    assert np.abs(scaled - static).max() < 0.01


@pytest.mark.parametrize("change, message", [
    ({"materials": {"fat": {"E": 10e3, "nu": 0.45}}}, r"no material given for tissue labels \[2\]"),
    ({"materials": {"fat": {"nu": 0.45}, "glandular": {"E": 1, "nu": 0.4}}}, "needs 'E'"),
    ({"materials": {"fat": {"E": 1e4, "nu": 0.45, "mu": 3}, "glandular": {"E": 1, "nu": 0.4}}}, "unknown fields"),
    ({"constraints": [{"nodes": "chest", "components": "y"}]}, "node set 'chest'"),
    ({"constraints": [{"nodes": [0, 99999]}]}, "outside"),
    ({"constraints": [{"nodes": [0], "components": "xq"}]}, "letters of 'xyz'"),
    ({"solver": {"method": "implicit"}}, "solver method"),
    ({"solver": {"steady_state_mm": 0.01}}, "steady_state_mm applies to the physical method"),
    ({"solver": {"increments": 3}}, "increments apply to the static method"),
    ({"solver": {"mass_scaling": True}}, "mass_scaling applies to the physical method"),
    ({"solver": {"method": "physical", "mass_scaling": "yes"}}, "true or false"),
    ({"solver": {"tolerance": 0.01}}, r"unknown solver settings \['tolerance'\]"),
])
def test_bad_cases_are_refused_with_the_reason(tmp_path, change, message):
    path, _, _ = _case(tmp_path, **change)
    with pytest.raises(ValueError, match=message):
        read_case(path)
    assert main(["simulate", str(path), "--out", str(tmp_path / "out")]) == 2


def test_simulate_starts_from_the_unloaded_state_of_the_imaged_shape(tmp_path):
    """A block hanging from its fixed top under gravity, imaged as it hangs: simulate with a
    reference_state unloads it (reported), starts pre-stressed and, with the same gravity and no
    other load, stays at the imaged shape; the unloaded shape is written beside it."""
    path, mesh, _ = _case(tmp_path, constraints=[{"nodes": "face_zhi"}], plates=[], gravity=[0, 0, -9.81],
                          reference_state={"imaged_gravity": [0, 0, -9.81], "tolerance_mm": 0.005},
                          solver={"method": "relaxation", "device": "cpu", "load_iterations": 300})
    assert main(["simulate", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    summary = json.loads((tmp_path / "out" / "solution.json").read_text())
    state = summary["reference_state"]
    assert state["iterations"] >= 2 and state["residual_mm"] <= 0.005 and state["largest_sag_mm"] > 0.01
    result = read_vtu(tmp_path / "out" / "deformed.vtu")
    assert np.abs(result.point_data["displacement"]).max() < 0.01
    unloaded = result.point_data["unloaded_displacement"]
    assert unloaded[:, 2].max() > 0.5 * state["largest_sag_mm"]  # the stress-free block hangs higher
    with pytest.raises(ValueError, match="reference_state"):
        read_case(_case(tmp_path, reference_state={"gravity": [0, 0, -9.81]})[0])
    with pytest.raises(ValueError, match="static reference solver"):
        read_case(_case(tmp_path, reference_state={"imaged_gravity": [0, 0, -9.81]}, solver={"method": "static"})[0])
