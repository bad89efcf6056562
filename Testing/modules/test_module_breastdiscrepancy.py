"""The BreastDiscrepancy module's Logic against a real MRML scene (slicer-core, headless, CPU).

A small compressed phantom with plate friction hidden in its truth (a copy without the truth
files), fitted without friction, goes through the module's steps: a round is diagnosed over the
whole library and names friction, the candidates table is the library's ranking, the overlays,
lines, skin model, regions and plots are nodes holding the round's figures; friction is accepted
and refitted, the gap shrinks (landmarks, the residual field in the contact bands) and the round
keeps its nodes. This is also the library's hidden-effect test on the CPU: the diagnosis and the
refit run as `breastbiomech diagnose --one-round` and `--add` (the non-interactive `--rounds` path:
Testing/integration/test_kill_resume_diagnosis.py and the null case). Bad inputs give a clear
message and leave the scene as it was."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("slicer")
import BreastDiscrepancy  # noqa: E402  (BreastBiomech/ is on the test path)
from BreastBiomechLib.mrml.frames import flip  # noqa: E402

pytestmark = [pytest.mark.mrml, pytest.mark.slow]

EFFECTS = ""  # the whole library


def _logic(scene, case, fit, out):
    logic = BreastDiscrepancy.BreastDiscrepancyLogic(scene)
    p = logic.getParameterNode()
    p["caseDirectory"], p["fitDirectory"], p["outputDirectory"] = str(case), str(fit), str(out)
    p["effects"], p["refineIterations"], p["device"] = EFFECTS, 1, "cpu"
    return logic, p


def _column(table, name):
    t = table.GetTable()
    column = t.GetColumnByName(name)
    return [column.GetValue(i) for i in range(t.GetNumberOfRows())]


def _lengths_mm(model):
    points = model.GetPolyData().GetPoints()
    return np.array([np.linalg.norm(np.subtract(points.GetPoint(2 * i + 1), points.GetPoint(2 * i)))
                     for i in range(points.GetNumberOfPoints() // 2)])


def test_a_hidden_friction_case_is_diagnosed_refitted_and_shown(scene, friction_case, tmp_path):
    case, fit = friction_case
    logic, p = _logic(scene, case, fit, tmp_path / "diagnosis")
    # the fixed model-error floor: the measured one (the panel's default) costs a solve on the
    # refined mesh, and its panel path is the next test's, its figures the command's tests'
    p["measuredFloor"] = False
    # Diagnose runs out of Slicer's process (`breastbiomech diagnose --one-round`): progress
    # arrives while it runs; its round, kept for the decision, is shown once it has ended
    worker = logic.startDiagnosis(p)
    events = []
    assert worker.wait(900, on_events=events.extend) == 0, worker.error
    messages = [e["message"] for e in events if e["event"] == "progress"]
    assert any(m.startswith("round 1: solving") for m in messages)
    table = logic.finishDiagnosis(p, worker)
    record = json.loads((tmp_path / "diagnosis" / "round-1.json").read_text())
    assert (tmp_path / "diagnosis" / "round-1-kept.npz").is_file()
    d = record["diagnosis"]
    assert d["verdict"] == "missing effect" and d["effect"] == "friction", d["sentence"]
    assert len([c for c in d["candidates"] if not c["skipped"]]) >= 7  # named among the whole library
    assert messages and "added" not in record  # nothing added before the user accepts
    # the table's order is the library's ranking; the verdict column names the proposal
    ranked = [c["name"] for c in d["candidates"]]
    assert _column(table, "effect") == ranked
    assert _column(table, "verdict")[0] == "missing effect"
    # each candidate's smallest detectable size, as the record has it (friction's: a finite mu)
    sizes = dict(zip(_column(table, "effect"), _column(table, "smallest size seen")))
    recorded = next(c for c in d["candidates"] if c["name"] == "friction")["detectable"]
    assert 0.0 < float(sizes["friction"]) == pytest.approx(recorded[0], rel=0.05)
    # friction's closest rival: the tested candidate whose signature correlates most with its own
    tested = [c["name"] for c in d["candidates"] if not c["skipped"] and c["name"] != "friction"]
    pairs = {o: d["correlations"].get(f"friction|{o}", d["correlations"].get(f"{o}|friction")) for o in tested}
    best = max(pairs, key=pairs.get)
    assert dict(zip(_column(table, "effect"), _column(table, "closest rival")))["friction"] == f"{best} {pairs[best]:.2f}"
    assert p.reference("candidatesTable") is table and p["candidate"] == "friction"
    # the landmark residual lines: from predicted to measured, their lengths the reported errors
    lines = p.reference("landmarkLines")
    reported = record["before"]["landmark_error_mm"]["per_landmark"]
    np.testing.assert_allclose(_lengths_mm(lines), list(reported.values()), atol=2e-3)
    from BreastBiomechLib.io.markups import read_markups

    measured = read_markups(case / "compressed" / "landmarks.mrk.json")  # LPS
    np.testing.assert_allclose(lines.GetPolyData().GetPoints().GetPoint(1), flip(measured.positions[0]), atol=1e-3)
    # seen in the slice views: projected onto the slice (a segment meets a plane in one point at most)
    display = lines.GetDisplayNode()
    assert display.GetVisibility2D() and display.GetSliceDisplayMode() == display.SliceDisplayProjection
    # the residual overlay: the field's magnitude on the measured grid, with a colour legend
    residual = p.reference("residualVolume")
    import SimpleITK as sitk
    from slicer.util import arrayFromVolume

    field = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "diagnosis" / "round-1-residual-before.nrrd")))
    np.testing.assert_allclose(arrayFromVolume(residual), np.linalg.norm(field, axis=-1), atol=1e-4)
    assert any(residual.GetNthDisplayNode(i).IsA("vtkMRMLColorLegendDisplayNode")
               for i in range(residual.GetNumberOfDisplayNodes()))
    assert p.reference("residualTransform").IsA("vtkMRMLGridTransformNode")
    # the skin model carries the signed distance; the regions are segments, contact bands among them
    skin = p.reference("skinModel").GetPolyData().GetPointData().GetArray("signed_distance_mm")
    assert skin is not None and skin.GetNumberOfTuples() > 50
    segmentation = p.reference("regions").GetSegmentation()
    names = {segmentation.GetNthSegment(i).GetName() for i in range(segmentation.GetNumberOfSegments())}
    assert any(n.startswith("contact") for n in names) and "sub-surface" in names
    # a candidate's predicted residual beside the measured one
    predicted = logic.showCandidate(p, "friction")
    assert p.reference("candidateVolume") is predicted and arrayFromVolume(predicted).max() > 0.1
    with pytest.raises(ValueError, match="not tested"):
        logic.showCandidate(p, "heterogeneity")  # skipped: the fit has a material per tissue

    # a refit cancelled midway (in its Gauss-Newton iteration) adds nothing: the round and the scene stay
    import time

    nodes = scene.GetNumberOfNodes()
    worker = logic.startAccept(p)
    while worker.running and not any("Gauss-Newton" in e.get("message", "") for e in worker.events):
        worker.poll()
        time.sleep(0.05)
    assert worker.running, worker.error
    assert worker.cancel(grace_s=10.0) < 10.0
    with pytest.raises(RuntimeError, match="cancelled"):
        logic.finishAccept(p, worker)
    assert "added" not in json.loads((tmp_path / "diagnosis" / "round-1.json").read_text())
    assert scene.GetNumberOfNodes() == nodes

    # accept: friction added and refitted in its own process from the round's kept diagnosis; the
    # gap shrinks; the plots hold before and after
    worker = logic.startAccept(p)
    assert worker.wait(900) == 0, worker.error
    record = logic.finishAccept(p, worker)
    assert record["added"] == "friction" and record["accepted"] == "verdict"
    # its profile interval is made with the refinement, when it is added (the round's own
    # confirmation refit, unrefined, carried the linearised one)
    assert next(c for c in d["candidates"] if c["name"] == "friction")["refit"]["interval_kind"] == "linearised"
    refit = next(c for c in record["diagnosis"]["candidates"] if c["name"] == "friction")["refit"]
    (low, high), = refit["interval"]
    assert refit["interval_kind"] == "profile" and low < refit["refined_values"][0] <= high
    # friction saturates above sticking: its profile interval is bounded by the data from below
    # only and reaches the range's top, so that it holds the hidden mu of 1.0; the confirmation
    # refit's linearised interval (estimate +- 1.96 sd, before the refinement) did not reach it
    assert refit["interval_open"] == [[False, True]] and high == 1.5 and low < 1.0
    assert refit["values"][0] + 1.96 * refit["sd"][0] < 1.0
    before, after = record["before"]["landmark_error_mm"]["mean"], record["after"]["landmark_error_mm"]["mean"]
    assert after < 0.7 * before
    # the residual displacement field before and after: its accuracy stated, and it shrinks in the
    # contact bands under the plates, where friction acts
    fields = record["before"]["residual_field"], record["after"]["residual_field"]
    for field in fields:
        assert (tmp_path / "diagnosis" / field["file"]).is_file()
        assert field["accuracy"]["known_rms_error_mm"] < field["accuracy"]["known_rms_mm"]
    contact = [name for name in fields[0]["regions"] if name.startswith("contact")]
    assert contact and all(fields[1]["regions"][name]["mean_mm"] < fields[0]["regions"][name]["mean_mm"]
                           for name in contact)
    written = (tmp_path / "diagnosis" / "report.md").read_text()
    assert "Missing effect: plate friction" in written and record["residual_picture"] in written
    errors = p.reference("landmarkErrorsTable")
    np.testing.assert_allclose(_column(errors, "error after (mm)"),
                               list(record["after"]["landmark_error_mm"]["per_landmark"].values()))
    assert p.reference("landmarkErrorsChart").GetNumberOfPlotSeriesNodes() == 2
    assert _column(p.reference("measuresTable"), "NMI") == pytest.approx([record["before"]["nmi"],
                                                                          record["after"]["nmi"]])
    histogram = p.reference("histogramTable")
    assert sum(_column(histogram, "share before")) == pytest.approx(1.0)
    np.testing.assert_allclose(_lengths_mm(p.reference("landmarkLines")),
                               list(record["after"]["landmark_error_mm"]["per_landmark"].values()), atol=2e-3)
    # every node of the round sits in its subject-hierarchy folder; showing round 1 again points at them
    from BreastBiomechLib.mrml.overlays import nodes_in_folder

    kept = nodes_in_folder(scene, logic._roundFolder(1))
    assert {n.GetAttribute("BreastDiscrepancy.Kind") for n in kept} >= {
        "residual-before", "residual-after", "lines-before", "lines-after", "skin-before", "skin-after", "regions",
        "candidates", "field-before", "field-after", "candidate-friction"}
    logic.showRound(p, 1)
    assert p.reference("residualVolume").GetAttribute("BreastDiscrepancy.Kind") == "residual-after"
    # Design next measurement, out of Slicer's process once the round is decided, for what round 1
    # could not tell apart among the chosen effects: with friction alone chosen (added: decided)
    # nothing is simulated, and the table, the verdict's line and the report say why (the design
    # itself, simulated, is the null case's test in test_discrepancy.py); the table sits in the
    # round's folder and is shown with the round
    p["effects"], p["designAcquisitions"] = "friction", "rotated"
    worker = logic.startDesign(p)
    assert worker.wait(900) == 0, worker.error
    design = logic.finishDesign(p, worker)
    made = json.loads((tmp_path / "diagnosis" / "design.json").read_text())
    assert made["round"] == 1 and made["designed_for"] == [] and made["acquisitions"] == []
    assert "friction" not in made["undecided"]
    [row] = _column(design, "effect")
    assert row == ("outside the chosen effects: " + ", ".join(made["undecided"]) if made["undecided"]
                   else "every tested candidate told apart")
    assert logic.verdictText(p).endswith(logic.designText(p)) and logic.designText(p).startswith("Next measurement: ")
    logic.showRound(p, 1)
    assert p.reference("designTable") is design and design.GetAttribute("BreastDiscrepancy.Kind") == "design"
    assert "## The next measurement" in (tmp_path / "diagnosis" / "report.md").read_text()
    p["effects"] = EFFECTS
    logic.setGlyphsVisible(p, True)
    assert p.reference("residualTransform").GetDisplayNode().GetVisibility()
    # the report names the effect; with a capture function its picture is in it
    report = logic.saveReport(p, capture=lambda path: shutil.copy(tmp_path / "diagnosis" / "round-1-residual.png",
                                                                  path))
    text = report.read_text()
    assert "Missing effect: plate friction" in text and "round-1-slice-views.png" in text
    assert logic.verdictText(p).startswith("Round 1: Missing effect")

    # a module Reload (a new Logic on the same scene, as after loading the saved scene): the rounds
    # are reached from the parameter node's output folder, the session taken up from its files
    again = BreastDiscrepancy.BreastDiscrepancyLogic(scene)
    q = again.getParameterNode()
    assert q.node is p.node and again.session is None
    assert again.roundNumbers(q) == [1]
    again.setGlyphsVisible(q, False)
    assert not q.reference("residualTransform").GetDisplayNode().GetVisibility()
    again.showRound(q, 1)
    assert again.session is not None and again.session.last["added"] == "friction"
    assert again.verdictText(q).startswith("Round 1: Missing effect")
    again.showCandidate(q, "skin")  # the round's diagnosis was kept: its candidates are shown after a Reload too
    assert q.reference("candidateVolume").GetAttribute("BreastDiscrepancy.Kind") == "candidate-skin"

    # the scene saved as a Slicer data bundle (.mrb) and opened again in a new scene: the rounds
    # are reached from the saved parameter node, a round and a candidate are shown
    import slicer

    saving = slicer.vtkMRMLApplicationLogic()
    saving.SetMRMLScene(scene)
    (tmp_path / "bundle").mkdir()
    assert saving.SaveSceneToSlicerDataBundleDirectory(str(tmp_path / "bundle"), None)
    assert saving.Zip(str(tmp_path / "scene.mrb"), str(tmp_path / "bundle"))
    opened = slicer.vtkMRMLScene()
    opened.RegisterNodeClass(slicer.vtkMRMLColorLegendDisplayNode())  # as the application's Colors module does
    colors = slicer.vtkMRMLColorLogic()
    colors.SetMRMLScene(opened)
    opening = slicer.vtkMRMLApplicationLogic()
    opening.SetMRMLScene(opened)
    (tmp_path / "unpacked").mkdir()
    assert opening.OpenSlicerDataBundle(str(tmp_path / "scene.mrb"), str(tmp_path / "unpacked"))
    reopened = BreastDiscrepancy.BreastDiscrepancyLogic(opened)
    r = reopened.getParameterNode()
    assert r["outputDirectory"] == str(tmp_path / "diagnosis") and reopened.roundNumbers(r) == [1]
    reopened.showRound(r, 1)
    assert reopened.verdictText(r).startswith("Round 1: Missing effect")
    assert r.reference("residualVolume").GetAttribute("BreastDiscrepancy.Kind") == "residual-after"
    reopened.showCandidate(r, "friction")
    assert r.reference("candidateVolume").GetAttribute("BreastDiscrepancy.Kind") == "candidate-friction"
    colors.SetMRMLScene(None)
    opened.Clear(True)


def test_bad_inputs_are_refused_and_leave_the_scene_as_it_was(scene, friction_case, tmp_path):
    from BreastBiomechLib.discrepancy import DiagnosisCancelled

    case, fit = friction_case
    nodes = scene.GetNumberOfNodes()
    logic, p = _logic(scene, case, fit, tmp_path / "out")
    p["outputDirectory"] = ""
    with pytest.raises(ValueError, match="choose an output folder"):
        logic.diagnose(p)
    p["outputDirectory"] = "relative/folder"
    with pytest.raises(ValueError, match="absolute path"):
        logic.diagnose(p)
    # a fit of another case
    other = shutil.copytree(fit, tmp_path / "other-fit")
    record = json.loads((other / "case.json").read_text())
    (other / "case.json").write_text(json.dumps({**record, "fingerprint": "0" * 64}))
    p["outputDirectory"], p["fitDirectory"] = str(tmp_path / "out"), str(other)
    with pytest.raises(ValueError, match="a fit of another case"):
        logic.diagnose(p)
    # a case without its measured volume
    broken = shutil.copytree(case, tmp_path / "broken")
    (broken / "compressed" / "mr.nrrd").unlink()
    p["caseDirectory"], p["fitDirectory"] = str(broken), str(fit)
    with pytest.raises(FileNotFoundError, match="no measured compressed image"):
        logic.diagnose(p)
    assert scene.GetNumberOfNodes() == nodes + 1  # the parameter node only
    with pytest.raises(ValueError, match="diagnose first"):
        logic.accept(p)
    with pytest.raises(ValueError, match="diagnose first"):
        logic.startDesign(p)
    # cancelling a diagnosis writes no round and adds no round node (the fixed floor: that a
    # Cancel keeps a measured floor is the null case's test, test_discrepancy.py)
    p["caseDirectory"], p["measuredFloor"] = str(case), False
    with pytest.raises(DiagnosisCancelled):
        logic.diagnose(p, progress=lambda message: "building" not in message)
    assert not (tmp_path / "out" / "round-1.json").exists()
    assert logic.roundNumbers(p) == []
    # a folder holding the floor a cancelled session measured (here one of the session's size) is
    # taken up again, not refused as "not empty", and the floor is read, not measured again
    features = len(logic.session.observations)
    (tmp_path / "out" / "floor.json").write_text(json.dumps({
        "discretisation": [0.1] * features, "feature_groups": ["everywhere (landmarks)"] * features, "tets": [1, 8],
        "seconds": 0.0, "case_dir": str(case), "fit_dir": str(fit)}))
    again, q = _logic(scene, case, fit, tmp_path / "out")
    q["measuredFloor"] = True  # the module's one parameter node: set back
    said = []
    again.openSession(q, progress=said.append)
    assert said and not any("measuring the model-error floor" in m for m in said)
    assert again.session.floor is not None
    # Breast Optimization's fit is taken only when it has one
    with pytest.raises(ValueError, match="no case folder"):
        logic.useOptimizationFit(p)


def test_closing_the_scene_drops_the_session(scene, tmp_path):
    """File > Close Scene removes the session's nodes (the measured volume, the rounds): the Logic
    forgets the session with them (selecting a candidate afterwards had failed on the missing
    volume); the next step opens it again from its output folder."""
    logic = BreastDiscrepancy.BreastDiscrepancyLogic(scene)
    logic.session, logic._key = object(), ("case", "fit", str(tmp_path))  # as openSession leaves them
    scene.Clear(False)  # what File > Close Scene does
    assert logic.session is None and logic._key is None
    with pytest.raises(ValueError, match="diagnose first"):
        logic.accept(logic.getParameterNode())


def test_a_logic_does_not_keep_its_scene_in_a_cycle():
    """The Logic's scene-close observer holds it weakly: a Logic and its scene are freed by their
    references alone (a callback holding the Logic made a cycle whose collection ran the callback
    inside the garbage collector on a half-freed Logic: a segmentation fault under pytest)."""
    import gc
    import weakref

    import slicer

    scene = slicer.vtkMRMLScene()
    logic = BreastDiscrepancy.BreastDiscrepancyLogic(scene)
    gone = weakref.ref(logic)
    del logic
    assert gone() is None  # freed at once: nothing but the caller held it
    scene.Clear(False)  # the observer finds no Logic and does nothing
    del scene
    gc.collect()
