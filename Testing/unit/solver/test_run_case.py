"""One way to run a case (issue 79): the command line, the discrepancy workflow's variants and the
phantom's truth run a case description through ``run_case`` and give its displacements to the
last bit on the CPU; the typed case description keeps the case-file format. The Breast
Simulation module's Logic is checked against ``run_case`` in Testing/modules/test_module_breastsimulation.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from BreastBiomechLib.io.cases import CaseDescription, case_from_dict, read_case
from BreastBiomechLib.io.meshes import read_vtu, write_vtu
from BreastBiomechLib.mesh.primitives import box_mesh
from BreastBiomechLib.solver import SolverSettings
from BreastBiomechLib.solver.run_case import run_case

SIDE = 20.0


def _description() -> tuple[CaseDescription, object]:
    """A 20 mm block on a fixed base pressed 3 mm by a plate on its top face, fat and gland."""
    mesh = box_mesh((SIDE, SIDE, SIDE), (3, 3, 3))
    mesh.cell_data["tissue"] = np.where(mesh.nodes[mesh.tets].mean(axis=1)[:, 0] < SIDE / 2, 1, 2).astype(np.int32)
    description = CaseDescription(
        mesh="block.vtu", materials={"fat": {"E": 3e3, "nu": 0.45}, "glandular": {"E": 9e3, "nu": 0.45}},
        constraints=[{"nodes": "face_zlo", "components": "xyz"}],
        plates=[{"name": "top", "point": [0.0, 0.0, SIDE], "normal": [0.0, 0.0, -1.0],
                 "displacement": [0.0, 0.0, -3.0], "slaves": "face_zhi"}],
        solver={"method": "relaxation", "tolerance_mm": 0.001, "load_iterations": 400})
    return description, mesh


def test_the_description_round_trips_through_its_json_and_refuses_unknown_entries(tmp_path):
    description, mesh = _description()
    again = CaseDescription.from_json(description.to_json())
    assert again == description
    write_vtu(tmp_path / "block.vtu", mesh)
    (tmp_path / "case.json").write_text(description.to_json())
    model, settings = read_case(tmp_path / "case.json")
    assert settings.method == "relaxation" and settings.relaxation.tolerance_mm == 0.001
    assert [p.name for p in model.loading.plates] == ["top"]
    with pytest.raises(ValueError, match=r"unknown case entries \['gravty'\]; a case holds .*'gravity'"):
        case_from_dict({**description.to_dict(), "gravty": [0, -9.81, 0]}, mesh)
    (tmp_path / "typo.json").write_text(json.dumps({**description.to_dict(), "plate": []}))
    with pytest.raises(ValueError, match=r"typo.json: unknown case entries \['plate'\]"):
        read_case(tmp_path / "typo.json")


def test_the_command_line_and_the_discrepancy_variants_run_a_case_as_run_case_does(tmp_path):
    from BreastBiomechLib.cli import main
    from BreastBiomechLib.discrepancy.variants import Variant, solve_variants

    description, mesh = _description()
    model, settings = description.build(mesh)
    settings = SolverSettings(method="relaxation", device="cpu", relaxation=settings.relaxation)
    reference = run_case(model, settings)
    assert reference.ok, reference.solution.message
    assert reference.displacement[:, 2].min() == pytest.approx(-3.0, abs=1e-3)

    write_vtu(tmp_path / "block.vtu", mesh)
    (tmp_path / "case.json").write_text(description.to_json())
    assert main(["simulate", str(tmp_path / "case.json"), "--out", str(tmp_path / "out"), "--device", "cpu",
                 "--quiet"]) == 0
    np.testing.assert_array_equal(read_vtu(tmp_path / "out" / "deformed.vtu").point_data["displacement"],
                                  reference.displacement)

    (outcome,) = solve_variants([Variant(model, model.materials, model.loading.plates)], mesh.nodes,
                                settings.relaxation, device="cpu")
    assert outcome.ok
    np.testing.assert_array_equal(outcome.displacement, reference.displacement)


def test_the_phantom_s_truth_is_run_case_of_its_truth_case(compressed_case_dir):
    """The conftest case's truth mesh carries the displacement ``compress_phantom`` solved; the
    truth's case (model and settings) run by ``run_case`` gives it again."""
    from BreastBiomechLib.phantom.compressed import TruthModel, truth_case

    truth_mesh = read_vtu(compressed_case_dir / "compressed" / "truth_mesh.vtu")
    recorded = truth_mesh.point_data.pop("displacement")
    truth = TruthModel(**json.loads((compressed_case_dir / "compressed" / "truth.json").read_text())["truth"])
    result = run_case(*truth_case(truth_mesh, truth, device="cpu"))
    assert result.ok
    np.testing.assert_allclose(result.displacement, recorded, rtol=0, atol=1e-6)
