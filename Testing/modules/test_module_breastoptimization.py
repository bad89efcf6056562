"""The BreastOptimization module's Logic against a real MRML scene (slicer-core, headless, CPU).

Through the nodes a user works with: a compressed case loaded from its folder (volumes,
landmarks, plates as markups planes whose RAS positions must give back the LPS plates of the
case), a fitting mesh model node, a few forward solves; pause and resume through the progress
callback, and the results as nodes checked against the library's own figures."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("slicer")
import BreastOptimization  # noqa: E402  (BreastBiomech/ is on the test path)
from BreastBiomechLib.io.images import read_image  # noqa: E402
from BreastBiomechLib.mesh.from_labels import MeshSettings, mesh_labels  # noqa: E402
from BreastBiomechLib.mrml import image_from_volume_node, tetmesh_to_model_node  # noqa: E402

pytestmark = [pytest.mark.mrml, pytest.mark.slow]


@pytest.fixture(scope="module")
def fitting_mesh(compressed_case_dir):
    """A coarse fitting mesh of the compressed test phantom (10 mm, tissues by voxel majority)."""
    return mesh_labels(read_image(compressed_case_dir / "labels.nrrd"),
                       MeshSettings(edge_mm=10.0, refine_interfaces=False)).mesh


def _set_up(scene, case_dir, mesh, out_dir, budget=3):
    logic = BreastOptimization.BreastOptimizationLogic(scene)
    p = logic.getParameterNode()
    logic.loadCompressedCase(p, str(case_dir))
    p.set_reference("inputMesh", tetmesh_to_model_node(mesh, scene, "Fitting mesh"))
    p["model"], p["freeNu"], p["budget"], p["device"] = "iso-hetero", False, budget, "cpu"
    p["toleranceMm"], p["outputDirectory"] = 0.05, str(out_dir)
    return logic, p


def test_a_loaded_case_gives_back_its_plates_and_images(scene, compressed_case_dir, fitting_mesh):
    logic, p = _set_up(scene, compressed_case_dir, fitting_mesh, "unused")
    plates = json.loads((compressed_case_dir / "compressed" / "plates.json").read_text())["plates"]
    back = logic.finalPlates(p, fitting_mesh)
    assert [b["name"] for b in back] == [plate["name"] for plate in plates]
    for b, plate in zip(back, plates):
        normal = np.asarray(plate["normal"]) / np.linalg.norm(plate["normal"])
        np.testing.assert_allclose(b["normal"], normal, atol=1e-9)  # towards the tissue, as in the file
        assert abs((np.asarray(b["point"]) - plate["point"]) @ normal) < 1e-6  # the same plane (LPS)
        assert b["edge"] == plate["edge"]
    measured = image_from_volume_node(p.reference("measuredVolume"))
    expected = read_image(compressed_case_dir / "compressed" / "mr.nrrd")
    np.testing.assert_allclose(measured.GetOrigin(), expected.GetOrigin(), atol=1e-6)
    assert p.reference("referenceLandmarks").GetNumberOfControlPoints() == 17
    fibre = logic.fibre(p)  # RAS (0, 0, 1) is LPS (0, 0, 1); R is -L
    assert fibre == pytest.approx((0.0, 0.0, 1.0))
    p["fibreR"], p["fibreS"] = 1.0, 0.0
    assert logic.fibre(p) == pytest.approx((-1.0, 0.0, 0.0))


def test_refusals_name_what_is_missing(scene, compressed_case_dir, fitting_mesh, tmp_path):
    logic = BreastOptimization.BreastOptimizationLogic(scene)
    p = logic.getParameterNode()
    with pytest.raises(ValueError, match="output folder"):
        logic.run(p)
    # what an empty folder widget reports, and relative paths (Slicer's working folder), are refused
    for unset in (".", "./", "fit", "out/fit"):
        p["outputDirectory"] = unset
        with pytest.raises(ValueError, match="choose an output folder|must be an absolute path"):
            logic.run(p)
    for unset in ("", "."):
        with pytest.raises(ValueError, match="choose the case folder"):
            logic.loadCompressedCase(p, unset)
    p["outputDirectory"] = str(tmp_path)
    with pytest.raises(ValueError, match="fitting mesh"):
        logic.run(p)
    with pytest.raises(FileNotFoundError, match="not a compressed case"):
        logic.loadCompressedCase(p, str(tmp_path))
    logic, p = _set_up(scene, compressed_case_dir, fitting_mesh, tmp_path)
    p["freeE"] = False
    with pytest.raises(ValueError, match="no parameter is free"):
        logic.run(p)


def test_a_case_with_further_states_is_fitted_jointly_and_each_state_shown(scene, two_state_case, compressed_case_dir,
                                                                           fitting_mesh, tmp_path):
    """conftest's two-state case (its phantom is the compressed test phantom, so the same fitting
    mesh): loading it shows the further state's measured volume; the fit is joint (in this
    process, and as the inputs an out-of-process fit reads), and each state's prediction and
    figures come back as nodes."""
    logic, p = _set_up(scene, two_state_case, fitting_mesh, tmp_path / "fit", budget=2)
    states = p.references("stateVolumes")
    assert [n.GetAttribute(BreastOptimization.STATE_ATTRIBUTE) for n in states] == ["lateral"]
    assert states[0].GetName() == "Measured lateral MR"
    np.testing.assert_allclose(image_from_volume_node(states[0]).GetOrigin(),
                               read_image(two_state_case / "states" / "lateral" / "mr.nrrd").GetOrigin(), atol=1e-6)
    inputs = tmp_path / "inputs"
    logic.writeInputs(p, inputs)
    for name in ("mr.nrrd", "plates.json", "landmarks.mrk.json", "force.json"):
        assert (inputs / "states" / "lateral" / name).is_file(), name
    result = logic.run(p)["result"]
    assert set(result.best.states) == {"compressed", "lateral"}
    table = p.reference("statesTable").GetTable()
    assert [table.GetValue(i, 0).ToString() for i in range(table.GetNumberOfRows())] == ["compressed", "lateral"]
    assert table.GetValue(1, 2).ToDouble() == pytest.approx(result.best.states["lateral"]["nmi"])
    predicted = p.references("statePredictedVolumes")
    assert [n.GetName() for n in predicted] == ["Predicted lateral MR"]
    recorded = json.loads((tmp_path / "fit" / "case.json").read_text())
    assert set(recorded["states"]) == {"compressed", "lateral"}
    # the lateral state's measured plate force scales the fitted moduli, as `optimise` does
    assert set(json.loads((tmp_path / "fit" / "force_scale.json").read_text())["states"]) == {"lateral"}
    # a case of one state loaded next: no further states
    logic.loadCompressedCase(p, str(compressed_case_dir))
    assert p.references("stateVolumes") == []


def test_pause_resume_and_results(scene, compressed_case_dir, fitting_mesh, tmp_path):
    """A run paused after its first batch keeps its evaluations and makes no result nodes;
    resumed, it replays them and finishes the budget; the result nodes agree with each other and
    with the optimisation's result."""
    logic, p = _set_up(scene, compressed_case_dir, fitting_mesh, tmp_path, budget=8)
    paused = logic.run(p, progress=lambda done, budget, best, phase: False, showBest=False)
    first = paused["result"]
    assert first.stopped == "cancelled" and "Resume" in paused["summary"]
    assert 0 < len(first.evaluations) < 8 and p.reference("predictedVolume") is None
    lines = (tmp_path / "evaluations.jsonl").read_text().splitlines()
    assert len(lines) == len(first.evaluations)

    outcome = logic.run(p, resume=True)
    result = outcome["result"]
    solved_now = {tuple(e.z) for e in result.evaluations} - {tuple(json.loads(line)["z"]) for line in lines}
    assert len(result.evaluations) == 8 and result.replayed == len(result.evaluations) - len(solved_now)
    assert [e.z for e in result.evaluations[:len(lines)]] == [json.loads(line)["z"] for line in lines]

    convergence = p.reference("convergenceTable").GetTable()
    assert convergence.GetValueByName(convergence.GetNumberOfRows() - 1, "forward solves").ToDouble() == 8
    assert convergence.GetValueByName(convergence.GetNumberOfRows() - 1,
                                      "best objective").ToDouble() == pytest.approx(result.best.objective)
    assert p.reference("convergenceChart").GetNumberOfPlotSeriesNodes() == 1

    predicted = image_from_volume_node(p.reference("predictedVolume"))
    measured = image_from_volume_node(p.reference("measuredVolume"))
    assert predicted.GetSize() == measured.GetSize()
    np.testing.assert_allclose(predicted.GetOrigin(), measured.GetOrigin(), atol=1e-6)

    parameters = p.reference("parametersTable").GetTable()
    names = [parameters.GetValueByName(r, "material").ToString() for r in range(parameters.GetNumberOfRows())]
    assert names == list(result.materials)
    glandular = names.index("glandular")
    assert parameters.GetValueByName(glandular, "E (Pa)").ToDouble() == pytest.approx(
        result.materials["glandular"]["E"])

    errors = p.reference("landmarkErrorsTable").GetTable()
    assert errors.GetNumberOfRows() == 17
    predicted_points, measured_points = p.reference("predictedLandmarks"), p.reference("measuredLandmarks")
    lines_node = p.reference("errorLines").GetPolyData()
    assert lines_node.GetNumberOfCells() == 17
    for row in range(17):
        label = errors.GetValueByName(row, "landmark").ToString()
        a = predicted_points.GetNthControlPointPosition(predicted_points.GetControlPointIndexByLabel(label))
        b = measured_points.GetNthControlPointPosition(measured_points.GetControlPointIndexByLabel(label))
        error = errors.GetValueByName(row, "error (mm)").ToDouble()
        assert error == pytest.approx(np.linalg.norm(np.subtract(a, b)), abs=1e-6)  # RAS distance = LPS distance
        assert lines_node.GetCellData().GetArray("error_mm").GetValue(row) == pytest.approx(error)
    assert "landmark error" in outcome["summary"]
    # the output folder is a complete fit folder of the loaded case: Breast Discrepancy takes it
    from BreastBiomechLib.discrepancy import load_fitted_case
    import BreastDiscrepancy

    fitted = load_fitted_case(compressed_case_dir, tmp_path, device="cpu")
    np.testing.assert_allclose(fitted.z, result.best.z)
    discrepancy = BreastDiscrepancy.BreastDiscrepancyLogic(scene)
    q = discrepancy.getParameterNode()
    discrepancy.useOptimizationFit(q)
    assert (q["caseDirectory"], q["fitDirectory"]) == (str(compressed_case_dir), str(tmp_path))


def test_fibre_plates_and_surface_choices(scene, compressed_case_dir, fitting_mesh, tmp_path):
    """The fibre direction (anisotropic models only) and the plates' offsets become free
    parameters; the surface objective runs without landmarks and the summary names the fitted
    plate offsets by the plates' names."""
    logic, p = _set_up(scene, compressed_case_dir, fitting_mesh, tmp_path, budget=2)
    p["freeFibre"], p["freeOffset"] = True, True
    plates = p.references("plates")
    assert len(plates) == 2
    space = logic.space(p, fitting_mesh)  # iso-hetero: no fibres to turn
    assert [k for k in space.keys if not k.startswith(("fat", "glandular", "muscle", "tumour", "skin"))] == [
        "plate1.offset", "plate2.offset"]
    p["model"] = "aniso-homo"
    assert logic.space(p, fitting_mesh).keys[-4:] == ["fibre.gamma", "fibre.alpha", "plate1.offset", "plate2.offset"]
    p["model"], p["freeE"], p["objective"] = "iso-hetero", False, "surface"
    p.set_reference("referenceLandmarks", None)
    p.set_reference("measuredLandmarks", None)
    outcome = logic.run(p)
    result = outcome["result"]
    assert len(result.evaluations) == 2 and all(0 < e.surface_mm < 20 for e in result.evaluations)
    assert result.best.objective == pytest.approx(result.best.surface_mm)
    assert f"{plates[0].GetName()} {result.geometry['plate_offsets_mm'][0]:+.2f}" in outcome["summary"]


def test_a_cohort_study_sent_to_a_dask_scheduler(scene, compressed_case_dir, tmp_path):
    """The study of a cases folder sent to a running Dask cluster by its scheduler's address (a
    local cluster of two CPU worker processes here): progress while it runs, the study table node
    with a row per fit, a broken case reported without stopping the others, refusals named."""
    import shutil

    from distributed import LocalCluster

    cases = tmp_path / "cases"
    shutil.copytree(compressed_case_dir, cases / "caseA")
    shutil.copytree(compressed_case_dir, cases / "broken")
    (cases / "broken" / "labels.nrrd").unlink()
    (cases / "notes").mkdir()  # not a case: no compressed/
    logic = BreastOptimization.BreastOptimizationLogic(scene)
    p = logic.getParameterNode()
    p["studyCasesDirectory"], p["studyOutputDirectory"] = str(cases), str(tmp_path / "study")
    p["studyModels"], p["studyBudgets"], p["studyEdgeMm"] = "iso-homo", "iso-homo=1", 12.0
    p["device"], p["toleranceMm"] = "cpu", 0.05
    assert [c.name for c in logic.studyCases(p)] == ["broken", "caseA"]
    p["studyBudgets"] = "iso-homo=two"
    with pytest.raises(ValueError, match="MODEL=SOLVES"):
        logic.runStudy(p)
    p["studyBudgets"] = "iso-homo=1"
    assert logic.studyPlacement(p).describe() == "this process, one task after another"

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        p["scheduler"] = cluster.scheduler_address
        assert logic.studyPlacement(p).describe() == f"the Dask cluster at {cluster.scheduler_address}"
        states = []
        run = logic.runStudy(p, progress=lambda state: states.append((state.done, state.total, dict(state.running))))
    assert states[-1][:2] == (4, 4) and any("caseA iso-homo cmaes" in running for _, _, running in states)
    assert [o.key for o in run.failed] == ["mesh/broken", "fit/broken/iso-homo-cmaes"] or \
        sorted(o.key for o in run.failed) == ["fit/broken/iso-homo-cmaes", "mesh/broken"]
    table = p.reference("studyTable").GetTable()
    assert table.GetNumberOfRows() == 1 and table.GetValueByName(0, "case").ToString() == "caseA"
    assert table.GetValueByName(0, "solves").ToDouble() == 1
    assert 1.0 < table.GetValueByName(0, "NMI").ToDouble() < 2.0
    p["studyCasesDirectory"] = str(tmp_path / "study")
    with pytest.raises(ValueError, match="holds no compressed case"):
        logic.studyCases(p)


def test_a_fit_out_of_process_reports_cancels_resumes_and_is_diagnosable(scene, compressed_case_dir, fitting_mesh,
                                                                        tmp_path):
    """The panel's Run: the fit runs as `breastbiomech optimise` in a process of its own (the
    chosen nodes written as a case folder in the output folder's inputs/); its progress arrives
    while it runs; Cancel stops the process and keeps the solves made; Resume goes on from them
    (replayed, not solved again) to the budget; the results are nodes as after a fit in process,
    and the output folder is a fit Breast Discrepancy takes, with the case it was made on."""
    import time

    logic, p = _set_up(scene, compressed_case_dir, fitting_mesh, tmp_path, budget=4)
    p["population"] = 2
    worker = logic.startRun(p)
    while worker.running and not any((e.get("fraction") or 0) > 0 for e in worker.events):
        worker.poll()
        time.sleep(0.05)  # until the first batch of solves has been written
    assert worker.running, worker.error
    seconds = worker.cancel(grace_s=10.0)
    assert seconds < 10.0 and not worker.running
    cancelled = logic.finishRun(p, worker)
    assert "Resume" in cancelled["summary"] and p.reference("predictedVolume") is None
    kept = (tmp_path / "evaluations.jsonl").read_text().splitlines()
    assert 2 <= len(kept) < 4 and p.reference("convergenceTable") is not None

    worker = logic.startRun(p, resume=True)
    progress = []
    assert worker.wait(600, on_events=progress.extend) == 0, worker.error
    outcome = logic.finishRun(p, worker)
    record = outcome["record"]
    assert record["evaluations"] == 4 and record["replayed"] == len(kept)
    assert [json.loads(line)["z"] for line in (tmp_path / "evaluations.jsonl").read_text().splitlines()[:len(kept)]] \
        == [json.loads(line)["z"] for line in kept]
    assert any("forward solves" in e.get("message", "") for e in progress)
    assert "landmark error" in outcome["summary"] and p.reference("predictedVolume") is not None
    assert p.reference("landmarkErrorsTable").GetTable().GetNumberOfRows() == 17
    assert p.reference("errorLines").GetPolyData().GetNumberOfCells() == 17
    parameters = p.reference("parametersTable").GetTable()
    glandular = [parameters.GetValueByName(r, "material").ToString()
                 for r in range(parameters.GetNumberOfRows())].index("glandular")
    assert parameters.GetValueByName(glandular, "E (Pa)").ToDouble() == pytest.approx(
        record["materials"]["glandular"]["E"])
    # the fit's case is its inputs, written from the nodes: Breast Discrepancy diagnoses that pair
    import BreastDiscrepancy
    from BreastBiomechLib.discrepancy import load_fitted_case

    discrepancy = BreastDiscrepancy.BreastDiscrepancyLogic(scene)
    q = discrepancy.getParameterNode()
    discrepancy.useOptimizationFit(q)
    assert q["fitDirectory"] == str(tmp_path) and q["caseDirectory"] == str((tmp_path / "inputs").resolve())
    fitted = load_fitted_case(q["caseDirectory"], tmp_path, device="cpu")
    np.testing.assert_allclose(fitted.z, record["best"]["z"])
    # resuming a folder that holds no fit started from the panel is refused
    p["outputDirectory"] = str(tmp_path / "empty")
    with pytest.raises(ValueError, match="no fit started from this panel"):
        logic.startRun(p, resume=True)
