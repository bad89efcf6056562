"""The BreastSimulation module's Logic against a real MRML scene (slicer-core, headless, CPU).

The checks go through the nodes a user edits (mesh model, materials table, plane markups) and
compare with the library solving the same model directly, so a wrong RAS/LPS conversion, a lost
table edit or a mis-oriented plate shows up as a different answer."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("slicer")
import BreastSimulation  # noqa: E402  (BreastBiomech/ is on the test path)
from BreastBiomechLib import labels  # noqa: E402
from BreastBiomechLib.mesh.primitives import hemi_ellipsoid_mesh  # noqa: E402
from BreastBiomechLib.mesh.tetmesh import TetMesh, boundary_nodes  # noqa: E402
from BreastBiomechLib.mrml import frames, tetmesh_to_model_node  # noqa: E402
from BreastBiomechLib.solver import DynamicRelaxation, ElementMaterials, Loading, Material, Model, solve  # noqa: E402
from BreastBiomechLib.solver.model import Constraint, PlateEdge  # noqa: E402
from BreastBiomechLib.solver.placement import compression_plates  # noqa: E402

pytestmark = pytest.mark.mrml


@pytest.fixture(scope="module")
def breast() -> TetMesh:
    """A coarse half ellipsoid (LPS mm) with a glandular core: two tissues."""
    mesh = hemi_ellipsoid_mesh((50.0, 40.0, 45.0), 10.0)
    centroids = mesh.nodes[mesh.tets].mean(axis=1)
    tissue = np.where(np.linalg.norm(centroids / [25.0, 20.0, 22.0], axis=1) < 1.0, labels.GLANDULAR.label,
                      labels.FAT.label)
    return TetMesh(mesh.nodes, mesh.tets, mesh.point_data, {"tissue": tissue.astype(np.int32)})


def _set_up(scene, mesh, compression=20.0):
    logic = BreastSimulation.BreastSimulationLogic(scene)
    p = logic.getParameterNode()
    p.set_reference("inputMesh", tetmesh_to_model_node(mesh, scene, "Breast"))
    logic.chooseDefaultNodeSets(p)
    p["compressionPercent"] = compression
    p["device"] = "cpu"
    logic.createDefaultMaterials(p)
    logic.createCompressionPlates(p)
    return logic, p


def test_defaults_follow_the_mesh(scene, breast):
    logic, p = _set_up(scene, breast)
    assert p["fixedNodeSet"] == "chest_wall" and p["contactNodeSet"] == "boundary"
    assert logic.nodeSetNames(p.reference("inputMesh")) == ["chest_wall", "surface"]
    table = p.reference("materials")
    assert [table.GetCellText(r, 0) for r in range(table.GetNumberOfRows())] == ["fat", "glandular"]
    plates = p.references("plates")
    assert [n.GetName() for n in plates] == ["Right plate", "Left plate"]
    width = np.ptp(breast.nodes[:, 0])
    assert [logic.plateTravel(n) for n in plates] == pytest.approx([0.1 * width, 0.1 * width])
    # placing again updates the same plane nodes
    p["compressionPercent"] = 30.0
    assert logic.createCompressionPlates(p) == plates
    assert logic.plateTravel(plates[0]) == pytest.approx(0.15 * width)


def test_run_matches_the_library_and_writes_results(scene, breast):
    logic, p = _set_up(scene, breast)
    table = p.reference("materials")
    table.GetTable().GetColumnByName("E (Pa)").SetValue(1, 35e3)  # the user stiffens the glandular tissue
    # tight enough that both solves below end within float32 noise of the same static solution (the
    # scene keeps the mesh points in float32, so the two relaxation paths are not bit-identical)
    p["tolerance"] = 1e-4
    messages = []
    result = logic.run(p, progress=lambda f, m: messages.append((f, m)))
    solution = result["solution"]
    assert solution.status == "completed", solution.message
    assert messages[0][0] == 0.0 and messages[-1] == (1.0, "completed")

    # the same model built with the library alone (LPS): plates, chest wall sliding (AP fixed) with a
    # 10 mm patch anchored and one at the SI extreme held LR, materials
    chest = np.flatnonzero(breast.point_data["chest_wall"])
    centre = chest[np.argmin(np.linalg.norm(breast.nodes[chest] - breast.nodes[chest].mean(axis=0), axis=1))]
    far = chest[np.argmax(np.abs(breast.nodes[chest, 2] - breast.nodes[centre, 2]))]  # SI extreme

    def patch(node):
        return chest[np.linalg.norm(breast.nodes[chest] - breast.nodes[node], axis=1) <= 10.0]

    # the plates' flat faces end the plate travel (auto chest clearance) anterior to the chest
    # wall (y = 0) in a rounded edge of that radius: they may touch every boundary node in front
    # of the chest wall
    boundary = np.flatnonzero(boundary_nodes(breast.tets, len(breast.nodes)))
    clearance = max(0.1 * np.ptp(breast.nodes[:, 0]), 5.0)
    assert breast.nodes[chest, 1].min() == pytest.approx(0.0)
    contact = boundary[breast.nodes[boundary, 1] < 0.0]
    plates = compression_plates(breast, "LR", 0.2, contact, names=("Right plate", "Left plate"),
                                extent_nodes=boundary)
    for plate in plates:
        plate.edge = PlateEdge([0.0, 1.0, 0.0], -clearance - plate.point[1], clearance)
    materials = ElementMaterials.from_tissues(breast.cell_data["tissue"], {
        labels.FAT.label: Material(10e3, 0.49), labels.GLANDULAR.label: Material(35e3, 0.49)})
    loading = Loading([Constraint.fixed(chest, (False, True, False)), Constraint.fixed(patch(centre)),
                       Constraint.fixed(patch(far), (True, False, False))], plates)
    direct = solve(Model(breast, materials, loading), device="cpu", relaxation=DynamicRelaxation(tolerance_mm=1e-4))
    np.testing.assert_allclose(solution.displacement, direct.displacement, atol=1e-3)
    # the Logic runs its case as every other path does (issue 79: one way to run a case)
    from dataclasses import replace

    from BreastBiomechLib.solver.run_case import run_case

    model, settings = logic.buildCase(p)
    again = run_case(model, replace(settings, device="cpu"), ke_ie_limit=logic.KE_IE_LIMIT)
    np.testing.assert_array_equal(solution.displacement, again.displacement)

    # deformed mesh node: RAS positions of the deformed nodes, displacement in RAS
    output = p.reference("outputMesh")
    grid = output.GetUnstructuredGrid()
    from vtk.util.numpy_support import vtk_to_numpy

    np.testing.assert_allclose(vtk_to_numpy(grid.GetPoints().GetData()),
                               frames.flip(breast.nodes + direct.displacement), atol=1e-3)
    np.testing.assert_allclose(vtk_to_numpy(grid.GetPointData().GetArray("displacement")),
                               frames.flip(direct.displacement), atol=1e-3)
    assert output.GetDisplayNode().GetActiveScalarName() == "displacement_magnitude"

    # no node behind a plate at the end; both plates press on the tissue
    final = breast.nodes + solution.displacement
    for plate in result["model"].loading.plates:
        moved = plate.point + plate.displacement
        assert ((final[plate.slave_nodes] - moved) @ plate.normal).min() > -1e-3
    forces = [solution.plate_forces[i] @ plate.normal for i, plate in enumerate(result["model"].loading.plates)]
    assert min(forces) > 0.2

    # history table and charts
    history = p.reference("history")
    columns = [history.GetColumnName(i) for i in range(history.GetNumberOfColumns())]
    assert columns == ["iteration", "kinetic energy (J)", "internal energy (J)", "Right plate force (N)",
                       "Left plate force (N)"]
    assert history.GetNumberOfRows() == len(solution.history["time"])
    last = history.GetNumberOfRows() - 1
    assert history.GetTable().GetValue(last, 3).ToDouble() == pytest.approx(
        solution.history["plate_forces"][-1][0] @ [1, 0, 0], rel=1e-9)
    chart = p.reference("forceChart")
    assert chart.GetNumberOfPlotSeriesNodes() == 2
    assert chart.GetNthPlotSeriesNode(0).GetTableNode() is history
    assert p.reference("energyChart").GetNumberOfPlotSeriesNodes() == 2
    assert "dynamic relaxation" in result["summary"] and "on cpu" in result["summary"]

    # a second run reuses the output, table and chart nodes
    counts = {c: scene.GetNumberOfNodesByClass(c) for c in ("vtkMRMLModelNode", "vtkMRMLTableNode",
                                                             "vtkMRMLPlotChartNode", "vtkMRMLPlotSeriesNode")}
    p["tolerance"] = 0.05
    logic.run(p)
    assert counts == {c: scene.GetNumberOfNodesByClass(c) for c in counts}


def test_plates_drawn_by_the_user(scene, breast):
    """A plane moved in the views moves the plate; a plane drawn with its normal pointing away
    from the breast still presses on it; a plane cutting into the breast is refused."""
    logic, p = _set_up(scene, breast)
    right, left = p.references("plates")
    model = logic.buildModel(p)
    assert model.loading.plates[0].normal == pytest.approx([1.0, 0.0, 0.0])  # LPS +x: towards the left

    origin = [0.0, 0.0, 0.0]
    right.GetOriginWorld(origin)
    right.SetOriginWorld(origin[0] + 3.0, origin[1], origin[2])  # 3 mm further right (RAS +x)
    right.SetNormalWorld(1.0, 0.0, 0.0)  # pointing away from the breast
    plate = logic.buildModel(p).loading.plates[0]
    assert plate.normal == pytest.approx([1.0, 0.0, 0.0])
    assert plate.point[0] == pytest.approx(breast.nodes[:, 0].min() - 3.0)
    assert plate.displacement == pytest.approx([logic.plateTravel(right), 0.0, 0.0])

    left.GetOriginWorld(origin)
    left.SetOriginWorld(origin[0] + 5.0, origin[1], origin[2])  # 5 mm into the breast (RAS +x is LPS -x)
    with pytest.raises(ValueError, match="'Left plate' cuts into the tissue.*5.00 mm"):
        logic.buildModel(p)


def test_bad_choices_are_refused_with_the_reason(scene, breast):
    logic = BreastSimulation.BreastSimulationLogic(scene)
    p = logic.getParameterNode()
    with pytest.raises(ValueError, match="choose the input mesh"):
        logic.run(p)
    surface = scene.AddNewNodeByClass("vtkMRMLModelNode", "SurfaceOnly")
    p.set_reference("inputMesh", surface)
    with pytest.raises(ValueError, match="no volumetric"):
        logic.buildModel(p)

    logic, p = _set_up(scene, breast)
    table = p.reference("materials")
    table.GetTable().RemoveRow(1)
    with pytest.raises(ValueError, match="no row for glandular"):
        logic.buildModel(p)
    logic.createDefaultMaterials(p)
    p.reference("materials").GetTable().GetColumnByName("nu").SetValue(0, 0.5)
    with pytest.raises(ValueError, match="materials table, fat: Poisson's ratio"):
        logic.buildModel(p)
    logic.createDefaultMaterials(p)

    p["fixAP"] = False
    with pytest.raises(ValueError, match="at least one direction"):
        logic.buildModel(p)
    p["fixAP"] = True
    p["fixedNodeSet"] = ""
    with pytest.raises(ValueError, match="rigid body"):
        logic.buildModel(p)
    p["fixedNodeSet"] = "pectoral"
    with pytest.raises(ValueError, match="'pectoral' is not a point array.*chest_wall"):
        logic.buildModel(p)
    p["fixedNodeSet"] = "chest_wall"
    p["method"] = "implicit"
    with pytest.raises(ValueError, match="relaxation or physical"):
        logic.run(p)
    p["method"] = "relaxation"
    if not logic.cudaAvailable():
        p["device"] = "cuda"
        with pytest.raises(ValueError, match="no CUDA GPU"):
            logic.run(p)
        assert "no CUDA GPU" in logic.deviceDescription()
    p.set_references("plates", [])
    with pytest.raises(ValueError, match="no plates"):
        logic.buildModel(p)


def test_cancel_keeps_earlier_results(scene, breast):
    logic, p = _set_up(scene, breast)
    result = logic.run(p, progress=lambda fraction, message: fraction < 0.005)
    assert result["solution"].status == "cancelled"
    assert p.reference("outputMesh") is None and p.reference("history") is None


def test_physical_time_run_reports_the_energy_verdict(scene, breast):
    """Explicit dynamics in physical time: a slow load passes the seed's KE/IE < 5 % check (and
    stops once settled), a fast one fails it and the verdict says what to change."""
    logic, p = _set_up(scene, breast, compression=10.0)
    p["method"] = "physical"
    p["totalTime"], p["settleTime"] = 0.02, 0.0
    fast = logic.run(p)
    assert fast["solution"].status == "energy criterion exceeded"
    assert "lengthen the loading time" in fast["summary"]
    assert [p.reference("history").GetColumnName(0)] == ["time (s)"]
    p["totalTime"], p["settleTime"], p["damping"], p["tolerance"] = 0.3, 1.0, 30.0, 0.05
    slow = logic.run(p)
    assert slow["solution"].status == "completed", slow["solution"].message
    assert "quasi-static" in slow["summary"]
    assert "settled at" in slow["summary"]  # stopWhenSettled (default): the settling phase ends early


def test_the_panel_and_a_case_file_of_the_same_scene_build_the_same_model(scene, breast, tmp_path):
    """One way to build a model: the Logic turns the scene into a case description, and the case
    file written from it (with the mesh as .vtu) builds the same model through `read_case`, with
    the new options (plate friction, a sliding chest wall, gravity) on."""
    import json

    from BreastBiomechLib.io.cases import read_case
    from BreastBiomechLib.io.meshes import write_vtu
    from BreastBiomechLib.solver.host_setup import merged_constraints

    logic, p = _set_up(scene, breast)
    p["plateFriction1"], p["plateFriction2"] = 0.4, 0.2
    p["chestWallMode"] = "sliding"
    p["gravity"] = "anterior (prone)"
    description, mesh = logic.caseDescription(p)
    write_vtu(tmp_path / "breast.vtu", mesh)
    (tmp_path / "case.json").write_text(json.dumps({"mesh": "breast.vtu", **description}))
    from_file, file_settings = read_case(tmp_path / "case.json")
    from_panel, panel_settings = logic.buildCase(p)
    np.testing.assert_allclose(from_file.mesh.nodes, from_panel.mesh.nodes, atol=1e-4)  # .vtu keeps float32
    np.testing.assert_array_equal(from_file.mesh.tets, from_panel.mesh.tets)
    for name in ("mu", "kappa", "eta", "fibre", "density"):
        np.testing.assert_allclose(getattr(from_file.materials, name), getattr(from_panel.materials, name))
    for a, b in zip(merged_constraints(from_file), merged_constraints(from_panel)):
        np.testing.assert_array_equal(a, b)
    assert [p.friction for p in from_panel.loading.plates] == [0.4, 0.2]
    for a, b in zip(from_file.loading.plates, from_panel.loading.plates):
        np.testing.assert_allclose([a.point, a.normal, a.displacement], [b.point, b.normal, b.displacement])
        np.testing.assert_array_equal(a.slave_nodes, b.slave_nodes)
        assert a.friction == b.friction and a.edge.to_dict() == b.edge.to_dict()
    (s_file,), (s_panel,) = from_file.loading.supports, from_panel.loading.supports
    assert s_panel.mode == "sliding" and np.array_equal(s_file.nodes, s_panel.nodes)
    np.testing.assert_allclose(s_file.normals, s_panel.normals, atol=1e-5)
    np.testing.assert_allclose(from_panel.loading.gravity, [0, -9.81, 0])
    assert from_file.loading.notes == from_panel.loading.notes and "sliding" in from_panel.loading.notes[0]
    assert file_settings.method == panel_settings.method == "relaxation"


def test_the_new_options_run_through_the_logic(scene, breast):
    """Friction, an elastic chest wall and a start from the unloaded prone shape through run():
    the support and the pre-stress are in the summary and the displacements are from the mesh as
    imaged; a start from the unloaded shape without gravity is refused."""
    logic, p = _set_up(scene, breast)
    p["plateFriction1"] = p["plateFriction2"] = 0.5
    p["chestWallMode"] = "elastic"
    p["chestWallNormalStiffness"], p["chestWallTangentialStiffness"] = 50.0, 5.0
    p["startUnloaded"] = True
    p["skinModulusKPa"], p["skinThicknessMm"] = 50.0, 2.0
    with pytest.raises(ValueError, match="needs the gravity"):
        logic.run(p)
    p["gravity"] = "anterior (prone)"
    messages = []
    result = logic.run(p, progress=lambda f, m: messages.append(m))
    solution = result["solution"]
    assert solution.status == "completed", solution.message
    assert any("unloaded" in m for m in messages)
    assert "chest wall springs 50 Pa/mm across, 5 Pa/mm along" in result["summary"]
    assert "skin E 50000 Pa, 2 mm: partial-volume weighting" in result["summary"]
    assert np.linalg.norm(solution.plate_tangential_forces, axis=1).max() > 0.0
    output = p.reference("outputMesh")
    assert output is not None and output.GetUnstructuredGrid().GetNumberOfPoints() == len(breast.nodes)


def test_the_panel_opens_without_starting_warp(scene):
    """Opening the panel says how the device will be chosen without starting warp (its start looks
    for CUDA and loads the kernel cache: seconds at every panel open); once warp has started in the
    session it names the device. A fresh interpreter, since the tests before this one started it."""
    import subprocess
    import sys

    script = ("import sys, slicer, BreastSimulation; "
              "text = BreastSimulation.BreastSimulationLogic(slicer.vtkMRMLScene()).deviceAtOpen(); "
              "contexts = [sys.modules.get(n) for n in ('warp._src.context', 'warp.context')]; "
              "started = any(getattr(c, 'runtime', None) is not None for c in contexts); "
              "print(repr(text), started)")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "PYTHONPATH": ":".join(sys.path)})
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip().endswith("False") and "looked up at the first Run" in run.stdout
    logic = BreastSimulation.BreastSimulationLogic(scene)
    logic.cudaAvailable()  # starts warp here
    assert logic.deviceAtOpen() == logic.deviceDescription()


def test_a_run_out_of_process_shows_progress_cancels_and_matches_the_run_in_process(scene, breast, tmp_path):
    """The panel's Run: the solve runs as `breastbiomech simulate` in a process of its own while
    Slicer stays live; its progress arrives as it runs; its results in the scene equal the
    in-process run's; a Cancel stops the process and leaves the scene's results as they were;
    a failing start says why."""
    logic, p = _set_up(scene, breast)
    p["method"], p["totalTime"], p["settleTime"], p["stopWhenSettled"] = "physical", 0.2, 0.05, False
    in_process = logic.run(p)["solution"]
    output, history = p.reference("outputMesh"), p.reference("history")
    expected = BreastSimulation.slicer.util.arrayFromModelPoints(output).copy()

    worker = logic.startRun(p, tmp_path / "run")
    seen = []
    assert worker.wait(300, on_events=seen.extend) == 0, worker.error
    progress = [e for e in seen if e["event"] == "progress"]
    assert len(progress) > 3 and progress[0]["fraction"] == 0.0 and progress[-1]["fraction"] == 1.0
    assert seen[-1]["event"] == "done" and worker.succeeded
    result = logic.finishRun(p, worker)
    assert result["solution"].status == "completed" and result["solution"].steps == in_process.steps
    assert p.reference("outputMesh") is output and p.reference("history") is history  # the same nodes, updated
    np.testing.assert_allclose(BreastSimulation.slicer.util.arrayFromModelPoints(output), expected, atol=1e-4)
    assert "completed" in result["summary"]

    # Cancel: the process ends within the grace period; the scene keeps the last results
    p["totalTime"] = 50.0  # long enough to be running when cancelled
    worker = logic.startRun(p, tmp_path / "cancelled")
    while worker.running and worker.last is None:  # until the solver reports
        worker.poll()
        time.sleep(0.05)
    seconds = worker.cancel(grace_s=10.0)
    assert not worker.running and worker.cancelled and seconds < 10.0 and worker.error == "cancelled"
    with pytest.raises(RuntimeError, match="cancelled"):
        logic.finishRun(p, worker)
    np.testing.assert_allclose(BreastSimulation.slicer.util.arrayFromModelPoints(output), expected, atol=1e-4)

    # a worker that fails says why, in the command's own words
    from BreastBiomechCommon.worker import CommandWorker

    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "case.json").write_text("{")
    broken = CommandWorker(["simulate", str(tmp_path / "broken" / "case.json"), "--out", str(tmp_path / "x")],
                           folder=str(tmp_path / "broken")).start()
    assert broken.wait(120) == 2 and not broken.succeeded
    with pytest.raises(RuntimeError, match="breastbiomech simulate: error: .*case.json"):
        logic.finishRun(p, broken)
