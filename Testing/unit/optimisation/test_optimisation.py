"""Material-parameter optimisation: the parameter space, the forward problem, the optimisers
recovering a truth inside the fitted family, the results file, budget, cancel and resume.

The fit runs on a small synthetic breast (optimisation.synthetic: a stair-stepped half ellipsoid
with a glandular core, a textured image) whose "measured" compressed image is the prediction at
known parameters: the truth lies in the family, so a fit must find it.
"""

from __future__ import annotations

import json

from pathlib import Path

import numpy as np
import pytest

from BreastBiomechLib.optimisation import FittingProblem, ParameterSpace, optimise
from BreastBiomechLib.optimisation.space import BOUNDS, REFERENCE_E, FreeParameter
from BreastBiomechLib.optimisation.synthetic import measured_at, synthetic_case
from BreastBiomechLib.solver import DynamicRelaxation

TRUTH = {"glandular.E": 30e3}
RELAXATION = DynamicRelaxation(load_iterations=400, tolerance_mm=0.002)


@pytest.fixture(scope="module")
def problem():
    """The fitting problem of glandular E (iso-hetero, only E free) on the small synthetic
    breast, whose measured image is the prediction at E_glandular = 30 kPa."""
    case = synthetic_case((40.0, 35.0, 40.0), element_mm=6.0, voxel_mm=(2.0, 2.0, 2.0))
    space = ParameterSpace.for_model("iso-hetero", ["fat", "glandular"], free=("E",))
    measured = measured_at(case, space, TRUTH, RELAXATION, device="cpu")
    return FittingProblem(space, case.mesh, case.undeformed, measured, case.planes, relaxation=RELAXATION,
                          device="cpu")


def test_unit_positions_map_onto_the_bounds_on_log_scales():
    E = FreeParameter("glandular", "E", *BOUNDS["E"])
    assert E.from_unit(0.0) == pytest.approx(100.0) and E.from_unit(1.0) == pytest.approx(1e6)
    assert E.from_unit(0.5) == pytest.approx(1e4)  # the geometric middle of 4 decades
    nu = FreeParameter("fat", "nu", *BOUNDS["nu"])
    assert nu.from_unit(0.0) == pytest.approx(0.45) and nu.from_unit(1.0) == pytest.approx(0.4999)
    assert nu.from_unit(0.5) == pytest.approx(0.5 - np.sqrt(0.05 * 1e-4))  # middle of log(0.5 - nu)
    for p, value in ((E, 31.6e3), (nu, 0.4987)):
        assert p.from_unit(p.to_unit(value)) == pytest.approx(value, rel=1e-12)
    assert E.from_unit(1.7) == pytest.approx(1e6)  # clipped to the bounds


def test_the_four_model_variants_free_what_the_seed_fits():
    tissues = ["fat", "glandular", "muscle", "tumour"]
    keys = {model: ParameterSpace.for_model(model, tissues).keys for model in
            ("iso-homo", "aniso-homo", "iso-hetero", "aniso-hetero")}
    assert keys["iso-homo"] == ["breast.nu"]  # fat's E is the reference; one material
    assert keys["aniso-homo"] == ["breast.nu", "breast.eta"]
    assert keys["iso-hetero"] == ["fat.nu", "glandular.E", "glandular.nu", "muscle.E", "muscle.nu", "tumour.E",
                                  "tumour.nu"]
    assert len(keys["aniso-hetero"]) == 11 and "fat.E" not in keys["aniso-hetero"]
    space = ParameterSpace.for_model("aniso-hetero", [1, 2, 3], fibre=(1.0, 0.0, 0.0))
    table = space.materials(np.full(space.dimension, 0.5))
    assert table["fat"]["E"] == REFERENCE_E and table["muscle"]["E"] == pytest.approx(1e4)
    tissue = np.array([1, 2, 3, 3])
    materials = space.element_materials(np.full(space.dimension, 0.5), tissue)
    assert np.all(materials.fibre == [1.0, 0.0, 0.0]) and np.all(materials.eta > 0)
    homogeneous = ParameterSpace.for_model("iso-homo", [1, 2]).element_materials([0.2], np.array([1, 2]))
    assert homogeneous.mu[0] == homogeneous.mu[1] and np.all(homogeneous.eta == 0)
    assert ParameterSpace.from_dict(space.to_dict()).keys == space.keys


def test_bad_spaces_are_refused():
    with pytest.raises(ValueError, match="unknown model"):
        ParameterSpace.for_model("aniso", ["fat"])
    with pytest.raises(ValueError, match="unknown free parameters"):
        ParameterSpace.for_model("iso-hetero", ["fat"], free=("G",))
    with pytest.raises(ValueError, match="below 0.5"):
        FreeParameter("fat", "nu", 0.45, 0.5)
    with pytest.raises(ValueError, match="name no parameter"):
        ParameterSpace.for_model("iso-homo", ["fat"], start={"glandular.E": 1e4})
    with pytest.raises(ValueError, match="3 coordinates"):
        ParameterSpace.for_model("iso-hetero", ["fat", "glandular"]).values([0.5])


def test_the_truth_maximises_nmi_and_fits_the_landmarks(problem):
    space = problem.space
    at_truth, softer, stiffer = problem.evaluate([space.unit(TRUTH), space.unit({"glandular.E": 12e3}),
                                                  space.unit({"glandular.E": 80e3})])
    assert at_truth.status == "completed" and at_truth.objective == pytest.approx(-at_truth.nmi)
    assert at_truth.nmi > softer.nmi + 1e-3 and at_truth.nmi > stiffer.nmi + 1e-3
    assert at_truth.ncc > 0.999
    assert at_truth.values["glandular.E"] == pytest.approx(30e3)


def test_a_failed_solve_is_logged_with_the_solvers_reason(problem, tmp_path):
    """A fit's log says why a solve failed, not only that it did: the solver's message is kept
    with the failed evaluation, written and read back; a completed one carries none."""
    from BreastBiomechLib.optimisation.record import read_evaluations

    case = synthetic_case((40.0, 35.0, 40.0), element_mm=6.0, voxel_mm=(2.0, 2.0, 2.0))
    hurried = FittingProblem(problem.space, case.mesh, case.undeformed, case.undeformed, case.planes,
                             relaxation=DynamicRelaxation(load_iterations=400, max_iterations=600), device="cpu")
    failed, = hurried.evaluate([problem.space.unit(TRUTH)])
    assert failed.status == "not converged" and failed.objective == hurried.failed_objective
    assert "dynamic relaxation stopped after" in failed.message and "raise max_iterations" in failed.message
    completed, = problem.evaluate([problem.space.unit(TRUTH)])
    assert completed.status == "completed" and completed.message == ""
    result = optimise(hurried, "cmaes", budget=3, seed=1, population=3, out_dir=tmp_path)
    assert result.failures == {"not converged": 3} == result.summary()["failures"]
    logged = read_evaluations(tmp_path / "evaluations.jsonl")
    assert [e.status for e in logged] == ["not converged"] * 3
    assert all("estimated error" in e.message for e in logged)


@pytest.mark.parametrize("optimiser, budget", [("hybrid", 30), ("cmaes", 36)])
def test_the_optimisers_recover_the_truth(problem, optimiser, budget, tmp_path):
    result = optimise(problem, optimiser, budget=budget, seed=1, out_dir=tmp_path)
    assert result.best.values["glandular.E"] == pytest.approx(TRUTH["glandular.E"], rel=0.05)
    assert result.materials["glandular"]["E"] == result.best.values["glandular.E"]
    assert result.materials["fat"]["E"] == REFERENCE_E
    assert len(result.evaluations) <= budget
    lines = (tmp_path / "evaluations.jsonl").read_text().splitlines()
    distinct = {tuple(e.z) for e in result.evaluations}  # a position asked for again is solved (and written) once
    assert len(lines) == len(distinct) and result.replayed == len(result.evaluations) - len(distinct)
    assert json.loads(lines[0])["z"] == result.evaluations[0].z
    summary = json.loads((tmp_path / "result.json").read_text())
    assert summary["best"]["objective"] == result.best.objective == min(e.objective for e in result.evaluations)


def test_cancel_and_resume_lose_nothing_and_end_where_an_uninterrupted_run_does(problem, tmp_path):
    whole = optimise(problem, "cmaes", budget=14, seed=4, population=4)
    calls = []

    def cancel_after_two_batches(done, budget, best, phase):
        calls.append(done)
        return len(calls) < 2

    first = optimise(problem, "cmaes", budget=14, seed=4, population=4, out_dir=tmp_path,
                     progress=cancel_after_two_batches)
    assert first.stopped == "cancelled" and len(first.evaluations) == 8
    with pytest.raises(FileExistsError, match="resume"):
        optimise(problem, "cmaes", budget=14, seed=4, population=4, out_dir=tmp_path)
    with pytest.raises(ValueError, match="seed differ"):
        optimise(problem, "cmaes", budget=14, seed=5, population=4, out_dir=tmp_path, resume=True)
    resumed = optimise(problem, "cmaes", budget=14, seed=4, population=4, out_dir=tmp_path, resume=True)
    assert resumed.replayed == 8 and resumed.stopped == "budget"
    assert [e.z for e in resumed.evaluations] == [e.z for e in whole.evaluations]
    assert resumed.best.objective == whole.best.objective
    assert len((tmp_path / "evaluations.jsonl").read_text().splitlines()) == 14


def test_a_best_that_no_longer_solves_alone_gives_way_to_the_next_best(problem, tmp_path, monkeypatch):
    """The outputs of a fit are made from its best parameters solved alone; where that solve
    inverts an element even with slower loads, the next best evaluation that solves stands in,
    the results file says so, and with none left the error names every failure."""
    from dataclasses import replace

    from BreastBiomechLib.optimisation.run import solve_best

    result = optimise(problem, "cmaes", budget=8, seed=2, population=4, out_dir=tmp_path)
    alone = problem.solve_alone
    refused = [result.best.z]

    def solve_alone(z, retries=2):
        solution = alone(z, retries)
        if any(np.allclose(z, r) for r in refused):
            return replace(solution, status="inverted elements", message="1 element(s) inverted (J <= 0)")
        return solution

    monkeypatch.setattr(problem, "solve_alone", solve_alone)
    ranked = sorted((e for e in result.evaluations if e.status == "completed"), key=lambda e: e.objective)
    standing, solution = solve_best(problem, result, tmp_path)
    assert solution.ok and standing.best is ranked[1]
    assert standing.materials["glandular"]["E"] == pytest.approx(ranked[1].values["glandular.E"])
    written = json.loads((tmp_path / "result.json").read_text())
    assert written["best"]["z"] == ranked[1].z
    assert written["stand_in"]["best_objective"] == result.best.objective and "inverted" in written["stand_in"]["reason"]
    unchanged, _ = solve_best(problem, standing, tmp_path)  # a best that solves stands as it is
    assert unchanged is standing
    refused[:] = [e.z for e in ranked]
    with pytest.raises(RuntimeError, match="no longer solve alone, nor the 5 next best"):
        solve_best(problem, result)


def test_the_command_fits_a_compressed_case_and_writes_its_results(compressed_case_dir, tmp_path, capsys):
    """`breastbiomech optimise` on the compressed phantom of conftest, with a small fitting mesh
    (the labels' body, tissues by voxel majority) and a budget of a few solves. The case is a
    copy without its truth (truth.json, the truth mesh): a fit never reads them."""
    import shutil

    from BreastBiomechLib.cli import main
    from BreastBiomechLib.cli.common import MODEL_CHOICES, OBJECTIVE_CHOICES
    from BreastBiomechLib.io.images import read_image
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels
    from BreastBiomechLib.optimisation.forward import OBJECTIVES
    from BreastBiomechLib.optimisation.space import MODELS

    assert MODEL_CHOICES == MODELS and OBJECTIVE_CHOICES == OBJECTIVES
    compressed_case_dir = Path(shutil.copytree(compressed_case_dir, tmp_path / "case"))
    for truth in ("truth.json", "truth_mesh.vtu"):
        (compressed_case_dir / "compressed" / truth).unlink()
    mesh = mesh_labels(read_image(compressed_case_dir / "labels.nrrd"),
                       MeshSettings(edge_mm=10.0, refine_interfaces=False)).mesh
    write_vtu(tmp_path / "fitting.vtu", mesh)
    out = tmp_path / "fit"
    arguments = ["optimise", str(compressed_case_dir), "--model", "iso-hetero", "--free", "E", "--budget", "3",
                 "--mesh", str(tmp_path / "fitting.vtu"), "--device", "cpu", "--tolerance-mm", "0.05",
                 "--out", str(out), "--json", "--quiet"]
    assert main(arguments) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["evaluations"] == 3 and summary["stopped"] == "budget" and summary["failed"] == 0
    assert 1.0 < summary["best"]["nmi"] < 2.0
    assert set(summary["materials"]) >= {"fat", "glandular", "muscle"}
    errors = summary["landmark_errors"]
    # the case's landmarks moved by millimetres (2.99 mm on average at 25 % compression since the
    # mesh repair removes flat caps, 2026-11-25), and the fit's error is below the largest move
    assert errors["displacement_mm"]["mean"] > 2.5 and 0 < errors["error_mm"]["mean"] < errors["displacement_mm"]["max"]
    for name in ("settings.json", "evaluations.jsonl", "result.json", "fitting_mesh.vtu", "predicted.nrrd",
                 "predicted_landmarks.mrk.json", "deformed_mesh.vtu", "landmark_errors.json", "convergence.png"):
        assert (out / name).is_file(), name
    predicted, measured = read_image(out / "predicted.nrrd"), read_image(compressed_case_dir / "compressed" / "mr.nrrd")
    assert predicted.GetSize() == measured.GetSize()
    # a second run into the same folder must resume, not overwrite
    assert main(arguments) == 2
    assert "resume it" in capsys.readouterr().err
    assert main(arguments + ["--resume", "--budget", "4"]) == 0
    assert json.loads(capsys.readouterr().out)["replayed"] == 3


def test_one_free_parameter_is_searched_by_batched_bracketing():
    """CMA-ES needs two dimensions (the cma package fails on one): a single free parameter (e.g.
    nu of a homogeneous model) is bracketed, one population per batch, down to the minimum."""
    from BreastBiomechLib.optimisation.forward import Evaluation
    from BreastBiomechLib.optimisation.record import EvaluationLog
    from BreastBiomechLib.optimisation.search import bracketing, cmaes

    batches = []

    def evaluate(positions):
        batches.append(len(positions))
        return [Evaluation([float(z[0])], {}, float((z[0] - 0.3137) ** 2), 1.0, 1.0, np.nan, np.nan, "completed",
                           1, 0.0) for z in positions]

    log = EvaluationLog(evaluate, budget=60)
    cmaes(log, np.array([0.5]), seed=0, population=8)
    assert log.best.z[0] == pytest.approx(0.3137, abs=1e-4)
    assert batches[0] == 8 and max(batches) <= 8 and len(log.evaluations) == 60
    converged = EvaluationLog(evaluate, budget=10_000)
    bracketing(converged, population=5, tolerance=1e-6)
    assert converged.best.z[0] == pytest.approx(0.3137, abs=1e-6) and len(converged.evaluations) < 10_000
    with pytest.raises(ValueError, match="at least 3"):
        bracketing(EvaluationLog(evaluate, budget=10), population=2)


def test_the_demo_replaces_its_earlier_fit_and_diagnosis_and_nothing_else(tmp_path, capsys):
    """`make demo` twice: the second run remakes the case and mesh, so the first run's fit and
    diagnosis are removed, not resumed; a folder that holds neither is refused, not deleted."""
    from BreastBiomechLib.cli.demo import clear_earlier_result

    fit = tmp_path / "fit"
    clear_earlier_result(fit)  # nothing there yet
    fit.mkdir()
    (fit / "settings.json").write_text("{}")
    (fit / "evaluations.jsonl").write_text("{}\n")
    clear_earlier_result(fit)
    assert not fit.exists() and "replacing" in capsys.readouterr().out
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="no earlier demo fit"):
        clear_earlier_result(other)
    assert (other / "notes.txt").read_text() == "keep"
    # the same for the diagnosis that follows the fit: its folder is known by diagnosis.json
    diagnosis = tmp_path / "diagnosis"
    diagnosis.mkdir()
    (diagnosis / "round-1.json").write_text("{}")
    with pytest.raises(FileExistsError, match="no earlier demo diagnosis"):
        clear_earlier_result(diagnosis, "diagnosis.json", "diagnosis")
    (diagnosis / "diagnosis.json").write_text("{}")
    clear_earlier_result(diagnosis, "diagnosis.json", "diagnosis")
    assert not diagnosis.exists() and "earlier run's diagnosis" in capsys.readouterr().out



def test_bench_optimise_figures_agree_with_its_log(tmp_path, capsys):
    """`bench optimise --json --out DIR`: one JSON line whose counts and best NMI are those of the
    evaluation log it keeps; the truth reproduces its own measured image (NMI 2); a second run
    into the same folder is refused, not mixed into the first."""
    import json

    from BreastBiomechLib.cli import main

    command = ["bench", "optimise", "--device", "cpu", "--radii", "40", "35", "40", "--element-mm", "8",
               "--voxel-mm", "3", "3", "3", "--budget", "4", "--population", "4", "--out", str(tmp_path / "fit"),
               "--json"]
    assert main(command) == 0
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    log = [json.loads(line) for line in (tmp_path / "fit" / "evaluations.jsonl").read_text().splitlines()]
    assert figures["evaluations"] == len(log) == 4
    assert figures["failed"] == sum(e["status"] != "completed" for e in log)
    assert figures["failed_by_status"] == {s: sum(e["status"] == s for e in log) for s in {e["status"] for e in log}
                                           if s != "completed"}
    assert figures["best_nmi"] == pytest.approx(max(e["nmi"] for e in log if e["status"] == "completed"), abs=1e-5)
    assert figures["truth_nmi"] == pytest.approx(2.0, abs=1e-4)
    after = list(figures["best_nmi_after"].values())
    assert after == sorted(after) and after[-1] == figures["best_nmi"]
    assert main(command) == 2
    assert "resume" in capsys.readouterr().err


def test_a_fit_still_improving_at_its_end_is_told_from_a_settled_one():
    """``recent_gain``: how far the best objective fell over the fit's last solves, which the demo
    report and `breastbiomech optimise` turn into "not settled" (CMA-ES on a quadratic: settled
    after 80 solves, not after 10)."""
    from BreastBiomechLib.optimisation.forward import Evaluation
    from BreastBiomechLib.optimisation.record import EvaluationLog
    from BreastBiomechLib.optimisation.run import OptimisationResult
    from BreastBiomechLib.optimisation.search import cmaes

    def evaluate(positions):
        return [Evaluation([float(v) for v in z], {}, float(np.sum((z - 0.3137) ** 2)), 1.0, 1.0, np.nan, np.nan,
                           "completed", 1, 0.0) for z in positions]

    def fit(budget):
        log = EvaluationLog(evaluate, budget=budget)
        cmaes(log, np.array([0.9, 0.1]), seed=0, population=5)
        return OptimisationResult(log.best, {}, log.evaluations, "budget", 0, 0.0)

    early, settled = fit(10).recent_gain(), fit(80).recent_gain()
    assert early > 1e-3 > settled >= 0.0
    failed = Evaluation([0.0, 0.0], {}, float("nan"), np.nan, np.nan, np.nan, np.nan, "inverted elements", 1, 0.0)
    done = evaluate(np.array([[0.3, 0.3]]))[0]
    assert OptimisationResult(done, {}, [failed] * 7 + [done] * 3, "budget", 0, 0.0).recent_gain() == np.inf
    assert np.isnan(OptimisationResult(done, {}, [done], "budget", 0, 0.0).recent_gain())


def test_a_fit_without_a_mesh_segments_the_case_s_mr_never_its_truth(compressed_case_dir, tmp_path, capsys):
    """With neither --mesh nor --labels the fit segments the case's MR from its seed points, as a
    clinic's case would be, and meshes that segmentation: the case here holds no truth at all
    (labels.nrrd and the truth files removed). A case without seed points is refused with the three
    ways to give a mesh named, and nothing is written."""
    import shutil

    from BreastBiomechLib.cli import main

    case = Path(shutil.copytree(compressed_case_dir, tmp_path / "case"))
    for truth in ("labels.nrrd", "compressed/truth.json", "compressed/truth_mesh.vtu"):
        (case / truth).unlink()
    arguments = ["optimise", str(case), "--model", "iso-homo", "--budget", "2", "--edge-mm", "10", "--device", "cpu",
                 "--tolerance-mm", "0.05", "--quiet"]
    assert main(arguments + ["--out", str(tmp_path / "fit")]) == 0
    for made in ("segmentation/labels.nrrd", "segmentation/segmentation.json", "fitting_mesh.vtu", "result.json"):
        assert (tmp_path / "fit" / made).is_file(), made
    (case / "seeds_muscle.mrk.json").unlink()
    assert main(arguments + ["--out", str(tmp_path / "unseeded")]) == 2
    error = capsys.readouterr().err
    assert "no seed points on the pectoral muscle" in error and "--mesh" in error and "--labels" in error
    assert "ground truth" in error and not (tmp_path / "unseeded").exists()


def test_cmaes_then_its_local_stage_settles_where_cmaes_alone_does_not():
    """The CPU demo's fit (19 solves): two whole generations of CMA-ES (population 5), then the
    local stage's batched gradients (d + 1 = 3 solves each; the first 2, its centre being the best
    point, answered from the log). On a quadratic it ends closer to the minimum than CMA-ES alone
    on the same budget (5e-5 against 2e-4 here), and no batch is a cut generation."""
    from BreastBiomechLib.optimisation.forward import Evaluation
    from BreastBiomechLib.optimisation.record import EvaluationLog
    from BreastBiomechLib.optimisation.search import cmaes, cmaes_local

    minimum = np.array([0.3137, 0.6421])
    batches = []

    def evaluate(positions):
        batches.append(len(positions))
        return [Evaluation([float(v) for v in z], {}, float(np.sum((z - minimum) ** 2)), 1.0, 1.0, np.nan, np.nan,
                           "completed", 1, 0.0) for z in positions]

    alone = EvaluationLog(evaluate, budget=19)
    cmaes(alone, np.array([0.5, 0.5]), seed=0, population=5)
    batches.clear()
    local = EvaluationLog(evaluate, budget=19)
    cmaes_local(local, np.array([0.5, 0.5]), seed=0, population=5)
    assert batches == [5, 5, 2, 3, 3] and len(local.evaluations) == 19
    assert [e.z for e in local.evaluations[:10]] == [e.z for e in alone.evaluations[:10]]  # the same generations
    assert local.best.objective < 0.5 * alone.best.objective
    assert np.allclose(local.best.z, minimum, atol=0.01)
