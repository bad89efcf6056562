"""The hidden-effect suite: its cases and their right verdicts, the effects outside the library
hidden in the truth, the measured copy that holds no truth, and the scoring."""

from __future__ import annotations

import json
import os
import socket

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.suite import (HIDDEN_EFFECTS, MEASURED_FILES, SuiteCase, SuiteSettings, case_result,
                                                measured_copy, scores_markdown, suite_cases, suite_scores)
from BreastBiomechLib.discrepancy.suite.cases import BY_REQUEST
from BreastBiomechLib.phantom.compressed import TruthModel


def test_the_suite_holds_null_single_two_and_unknown_effects_on_five_anatomies():
    cases = suite_cases()
    assert len(cases) == 5 * (len(HIDDEN_EFFECTS) - len(BY_REQUEST))  # those by request only when named
    assert not {c.hidden.name for c in cases} & set(BY_REQUEST)
    assert {c.hidden.name for c in suite_cases(effects=BY_REQUEST)} == set(BY_REQUEST)
    assert len({c.name for c in cases}) == len({c.seed for c in cases}) == len(cases)
    kinds = {h.name: h.kind for h in HIDDEN_EFFECTS.values()}
    assert list(kinds.values()).count("unknown") >= 2 and "null" in kinds.values() and "two" in kinds.values()
    assert HIDDEN_EFFECTS["stiff-band"].right_verdict == "unexplained discrepancy"
    assert HIDDEN_EFFECTS["null"].right_verdict == "no significant discrepancy"
    assert HIDDEN_EFFECTS["skin"].right_verdict == "missing effect"
    for hidden in HIDDEN_EFFECTS.values():  # every hidden effect is a valid truth
        TruthModel(**hidden.truth)
    with pytest.raises(ValueError, match="unknown hidden effects"):
        suite_cases(effects=["wind"])
    with pytest.raises(ValueError, match="Table 1 presets"):
        suite_cases(anatomies=[7])


@pytest.fixture(scope="module")
def truth_model(compressed_case_dir):
    """The seed's compression of the conftest case's truth mesh, as the truth simulation builds it."""
    from BreastBiomechLib.io.cases import case_from_dict, compression_case
    from BreastBiomechLib.io.meshes import read_vtu

    mesh = read_vtu(compressed_case_dir / "compressed" / "truth_mesh.vtu")
    spec = compression_case(mesh, "truth_mesh.vtu", "LR", 0.25)
    return case_from_dict(spec, mesh)


def test_the_unknown_effects_change_the_truth_where_they_say(truth_model):
    from BreastBiomechLib.labels import MUSCLE
    from BreastBiomechLib.phantom.compressed import with_hidden_effects

    model, settings = truth_model
    plain, _ = with_hidden_effects(model, TruthModel())
    banded, _ = with_hidden_effects(model, TruthModel(stiff_band=[4.0, 15.0]))
    ratio = banded.materials.mu / plain.materials.mu
    stiff = np.isclose(ratio, 4.0)
    assert np.all(stiff | np.isclose(ratio, 1.0)) and 0.05 < stiff.mean() < 0.5
    np.testing.assert_allclose(banded.materials.kappa[stiff] / plain.materials.kappa[stiff], 4.0)
    mesh = model.mesh
    assert not np.any(stiff & (np.asarray(mesh.cell_data["tissue"]) == MUSCLE.label))
    # the band is a slab: its elements' centroids lie within half its thickness of one plane
    centroids = mesh.nodes[mesh.tets].mean(axis=1)
    normal = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    depth = centroids[stiff] @ normal
    assert np.ptp(depth) <= 15.0 + 1e-9

    shifted, _ = with_hidden_effects(model, TruthModel(chest_wall_shift_mm=[0.0, -4.0, 0.0]))
    assert shifted.loading.constraints
    for before, after in zip(plain.loading.constraints, shifted.loading.constraints):
        np.testing.assert_array_equal(before.nodes, after.nodes)
        np.testing.assert_allclose(after.values[after.mask], np.broadcast_to([0.0, -4.0, 0.0], after.values.shape)[after.mask])
    assert TruthModel(stiff_band=[4, 15], chest_wall_shift_mm=[0, -4, 0]).hidden_effects == [
        "stiff band x4, 15 mm", "chest-wall shift [0.0, -4.0, 0.0] mm"]


def test_the_seed_s_rig_holds_one_plate_against_the_breast(compressed_case_dir):
    """moving_plate "second": the first plate stays where it starts, touching the nearest skin it
    can touch (not the breast's widest point in the band by the chest that plates leave free);
    the second travels the whole closure, and the suite tilts that one where it hides a tilt."""
    from BreastBiomechLib.discrepancy.suite.runner import hidden_truth
    from BreastBiomechLib.io.cases import case_from_dict, compression_case
    from BreastBiomechLib.io.meshes import read_vtu

    mesh = read_vtu(compressed_case_dir / "compressed" / "truth_mesh.vtu")
    both, _ = case_from_dict(compression_case(mesh, "truth_mesh.vtu", "LR", 0.25), mesh)
    seed, _ = case_from_dict(compression_case(mesh, "truth_mesh.vtu", "LR", 0.25, moving="second"), mesh)
    held, moving = seed.loading.plates
    assert not np.any(held.displacement)
    np.testing.assert_allclose(moving.displacement, 2 * both.loading.plates[1].displacement)
    gaps = held.gaps(mesh.nodes[held.slave_nodes])
    assert gaps.min() == pytest.approx(0.0, abs=1e-5)
    assert held.point[0] >= both.loading.plates[0].point[0]  # moved onto the tissue it can touch
    tilt = SuiteCase(1, HIDDEN_EFFECTS["plate-tilt"])
    assert hidden_truth(tilt, SuiteSettings())["plate_tilt_deg"] == [[4.0, 0.0], [0.0, 0.0]]
    assert hidden_truth(tilt, SuiteSettings(moving_plate="second"))["plate_tilt_deg"] == [[0.0, 0.0], [4.0, 0.0]]
    from BreastBiomechLib.discrepancy.suite.varied import sized_effect

    pivoted = SuiteCase(1, sized_effect("plate-tilt", np.random.default_rng(0)))  # its pivot goes with its turn
    moved = hidden_truth(pivoted, SuiteSettings(moving_plate="second"))
    assert moved["plate_pivot_mm"] == pivoted.hidden.truth["plate_pivot_mm"][::-1] != [[0.0, 0.0, 0.0]] * 2
    with pytest.raises(ValueError, match="moving plate is one of"):
        TruthModel(moving_plate="lateral")
    with pytest.raises(ValueError, match="moving_plate is one of"):
        SuiteSettings(moving_plate="lateral")


def test_the_hidden_chest_wall_holds_the_breast_along_the_chest(truth_model):
    """The suite's hidden chest wall: held across the local chest surface, with springs of
    3.4 kPa/mm along it, in place of the seed's anterior-posterior hold."""
    from BreastBiomechLib.phantom.compressed import with_hidden_effects

    model, settings = truth_model
    held, _ = with_hidden_effects(model, TruthModel(**HIDDEN_EFFECTS["chest-wall"].truth))
    (support,) = held.loading.supports
    assert support.mode == "sliding" and support.tangential_stiffness == 3400.0
    np.testing.assert_array_equal(support.nodes, np.unique(model.mesh.node_set("chest_wall")))


def test_bad_unknown_effects_are_refused():
    with pytest.raises(ValueError, match="stiff_band"):
        TruthModel(stiff_band=[4.0])
    with pytest.raises(ValueError, match="stiff_band"):
        TruthModel(stiff_band=[-1.0, 10.0])
    with pytest.raises(ValueError, match="chest_wall_shift_mm"):
        TruthModel(chest_wall_shift_mm=[0.0, float("nan"), 0.0])


def test_the_measured_copy_holds_only_what_a_clinic_has(compressed_case_dir, tmp_path):
    from BreastBiomechLib.io.markups import read_markups

    copy = measured_copy(compressed_case_dir, tmp_path / "measured")
    held = {str(p.relative_to(copy)) for p in copy.rglob("*") if p.is_file()}
    assert held <= set(MEASURED_FILES)
    assert {"mr.nrrd", "compressed/mr.nrrd", "compressed/plates.json", "landmarks.mrk.json"} <= held
    assert not any("truth" in name or "labels" in name or "signal" in name or "fraction" in name for name in held)
    # landmarks as a person marks them: the truth's moved by a localisation error of the given sd
    marked = measured_copy(compressed_case_dir, tmp_path / "marked", landmark_noise_mm=0.5, seed=3)
    errors = []
    for name in ("landmarks.mrk.json", "compressed/landmarks.mrk.json"):
        exact, noisy = read_markups(compressed_case_dir / name), read_markups(marked / name)
        assert noisy.labels == exact.labels
        np.testing.assert_array_equal(read_markups(copy / name).positions, exact.positions)
        errors.append(noisy.positions - exact.positions)
    errors = np.concatenate(errors).ravel()
    assert 0.3 < errors.std() < 0.7 and np.abs(errors.mean()) < 0.25
    assert (marked / "compressed" / "plates.json").read_bytes() == (copy / "compressed" / "plates.json").read_bytes()
    with pytest.raises(ValueError, match="localisation error"):
        measured_copy(compressed_case_dir, tmp_path / "bad", landmark_noise_mm=-1.0)


def test_a_hidden_plate_tilt_is_not_in_the_case_s_record(compressed_case_dir, tmp_path):
    """The case records the plates' nominal poses (as the compression gives them), so a tilt in
    the truth stays hidden from the fit; the truth's actual planes are in its summary. The
    record also carries the compressed scan's posture, here a posture change to upright."""
    from BreastBiomechLib.phantom.compressed import compress_phantom
    from BreastBiomechLib.phantom.compressed_files import read_compressed, write_compressed
    from BreastBiomechLib.phantom.files import read_phantom

    truth = TruthModel(compression=0.25, edge_mm=6.0, plate_tilt_deg=[[3.0, 0.0], [0.0, 0.0]])
    compressed = compress_phantom(read_phantom(compressed_case_dir), truth, device="cpu")
    recorded = read_compressed(compressed_case_dir).plates
    for mine, nominal in zip(compressed.plates, recorded):
        np.testing.assert_allclose(mine["normal"], nominal["normal"], atol=1e-12)
        np.testing.assert_allclose(mine["point"], nominal["point"], atol=1e-9)
    actual = compressed.summary["plates"]
    tilt = np.degrees(np.arccos(np.clip(np.dot(actual[0]["normal"], recorded[0]["normal"]), -1, 1)))
    assert tilt == pytest.approx(3.0, abs=1e-6)
    np.testing.assert_allclose(actual[1]["normal"], recorded[1]["normal"], atol=1e-12)
    np.testing.assert_allclose(compressed.gravity, [0.0, -9.81, 0.0])

    upright = TruthModel(gravity=[0.0, -9.81, 0.0], compression_gravity=[0.0, 0.0, -9.81])
    assert upright.scan_gravity == [0.0, 0.0, -9.81]
    compressed.gravity = upright.scan_gravity
    write_compressed(compressed, tmp_path, overview=False)
    np.testing.assert_allclose(read_compressed(tmp_path).gravity, [0.0, 0.0, -9.81])


def _round(verdict, effect=None, added=None, before=(2.0, 1.20), after=None, refit=None):
    record = {"diagnosis": {"verdict": verdict, "effect": effect, "overall": {"statistic": 50.0, "dof": 40,
                                                                              "p_value": 0.1}},
              "before": {"landmark_error_mm": {"mean": before[0]}, "nmi": before[1]}}
    if added:
        record["added"] = added
        record["after"] = {"landmark_error_mm": {"mean": after[0]}, "nmi": after[1]}
        record["diagnosis"]["candidates"] = [{"name": added, "refit": refit or {}}]
    return record


def test_cases_are_scored_against_the_effect_their_truth_hides():
    def result(hidden, rounds, truth_nmi=1.30):
        return case_result(SuiteCase(1, HIDDEN_EFFECTS[hidden]), rounds, truth_nmi, {}, {"fit": 10.0})

    none = _round("no significant discrepancy")
    friction = _round("missing effect", "friction", "friction", after=(0.8, 1.26),
                      refit={"values": [0.2], "refined_values": [0.5], "sd": [0.06]})
    tilt = _round("missing effect", "plate-tilt", "plate-tilt", before=(0.8, 1.26), after=(0.5, 1.28))
    unexplained = _round("unexplained discrepancy")
    results = [result("null", [none]), result("null", [friction, none]), result("friction", [friction, none]),
               result("friction", [unexplained]), result("friction+plate-tilt", [friction, tilt, none]),
               result("stiff-band", [unexplained]), result("chest-wall-shift", [friction, none]),
               {"case": "anatomy2-skin", "error": "RuntimeError: boom"}]
    assert [r.get("correct") for r in results] == [True, False, True, False, True, True, False, None]
    assert [r.get("final") for r in results[:7]] == ["none", "none", "none", "unexplained", "none", "unexplained", "none"]
    # every round scored: the right effect added, then a false "unexplained", is not right; nor
    # an effect added in the last round the rounds allowed (nothing tested the model with it)
    later = [result("friction", [friction, unexplained]), result("friction", [friction])]
    assert [r["correct"] for r in later] == [False, False]
    assert [r["final"] for r in later] == ["unexplained", "unconfirmed"]
    assert [r["false_unexplained_after_right"] for r in later] == [True, False]
    # the refined estimate against the truth's mu 0.6: -0.1, inside 1.96 sd (0.118)
    assert results[2]["estimates"]["friction"]["error"] == pytest.approx([-0.1])
    assert results[2]["estimates"]["friction"]["in_interval"] and results[4]["estimates"]["friction"]["in_interval"]
    assert "friction" not in results[6]["estimates"]  # no true friction in a chest-wall shift
    narrow = result("friction", [_round("missing effect", "friction", "friction", after=(0.8, 1.26),
                                        refit={"refined_values": [1.5], "sd": [0.05]}), none])
    assert narrow["correct"] and not narrow["estimates"]["friction"]["in_interval"]
    # a recorded (profile) interval is scored as it is: an estimate far below a saturating truth
    # whose interval is open above holds it; the sd is not used then
    profiled = result("friction", [_round("missing effect", "friction", "friction", after=(0.8, 1.26),
                                          refit={"refined_values": [0.3], "sd": [0.01],
                                                 "interval": [[0.2, 1.5]]}), none])
    assert profiled["estimates"]["friction"]["in_interval"]
    assert profiled["estimates"]["friction"]["interval"] == [[0.2, 1.5]]
    # an interval the model-error floor widened: the data's own is scored beside it
    floored = result("friction", [_round("missing effect", "friction", "friction", after=(0.8, 1.26),
                                         refit={"refined_values": [1.5], "sd": [0.01], "interval": [[0.09, 1.5]],
                                                "data_interval": [[1.27, 1.5]]}), none])
    assert floored["estimates"]["friction"]["in_interval"] and not floored["estimates"]["friction"]["in_data_interval"]
    assert profiled["estimates"]["friction"]["in_data_interval"]  # none kept: the recorded interval
    assert suite_scores([floored, profiled])["truth_in_data_interval"] == pytest.approx(1 / 2)
    later_scores = suite_scores(results[:7] + later + [narrow])
    assert later_scores["false_unexplained_after_right"] == pytest.approx(1 / 5)  # of the 5 with friction added
    assert later_scores["truth_in_interval"] == pytest.approx(4 / 5)
    assert later_scores["friction_within_0.2"] == pytest.approx(4 / 5)
    assert results[2]["landmark_error_fall"] == pytest.approx(0.6)
    assert results[2]["nmi_gap_closed"] == pytest.approx(0.6)
    assert results[4]["landmark_error_fall"] == pytest.approx(0.75)   # before the first round, after the last
    # against the truth's exact landmarks where the suite gives them, the measured ones kept beside
    scored = case_result(SuiteCase(1, HIDDEN_EFFECTS["friction"]), [friction, none], 1.3, {}, {},
                         {"before": 1.0, "after": 0.2})
    assert scored["landmark_error_fall"] == pytest.approx(0.8)
    assert (scored["measured_landmark_error_before_mm"], scored["measured_landmark_error_after_mm"]) == (2.0, 0.8)
    scores = suite_scores(results)
    assert scores["false_alarms"] == pytest.approx(0.5) and scores["null_cases"] == 2
    assert scores["right_verdicts"] == pytest.approx(3 / 5) and scores["hidden_cases"] == 5
    assert scores["right_by_kind"] == {"null": [1, 2], "single": [1, 2], "two": [1, 1], "unknown": [1, 2]}
    assert scores["landmark_error_fall"] == pytest.approx((0.6 + 0.75) / 2)
    assert scores["confusion"]["friction"] == {"friction": 1, "none": 0, "unexplained": 1}
    assert scores["failed"] == [{"case": "anatomy2-skin", "error": "RuntimeError: boom"}]
    text = scores_markdown(scores, results)
    assert "| friction | 1 | 0 | 1 |" in text and "failed: RuntimeError: boom" in text
    assert "| friction+plate-tilt | friction → none |" not in text and "| anatomy1-friction | friction → none |" in text
    assert "of 2 (95 % CI 9%-91%)" in text  # the false alarms: 1 of 2 null cases


def test_a_refinement_the_truth_holds_is_right_named_or_not_and_wrong_where_it_does_not():
    """The varied suite's gravity truths lean from the posture their case records ("upright"):
    gravity turned from it is then right whether a round names it or not; in a truth that does
    not lean it is a false naming."""
    from BreastBiomechLib.discrepancy.suite.scores import false_naming
    from BreastBiomechLib.discrepancy.suite.varied import varied_cases

    leaning = next(c for c in varied_cases(20) if c.hidden.name == "gravity")
    assert leaning.hidden.optional == ("gravity-direction",)
    assert leaning.hidden.truth["recorded_gravity"] == [0.0, 0.0, -9.81] != leaning.hidden.truth["compression_gravity"]
    assert TruthModel(**leaning.hidden.truth).recorded_scan_gravity == [0.0, 0.0, -9.81]
    upright = SuiteCase(1, HIDDEN_EFFECTS["gravity"])  # the fixed suite's: compressed exactly upright, so recorded
    assert upright.hidden.optional == ()
    gravity = _round("missing effect", "gravity", "gravity", after=(0.8, 1.26))
    turned = _round("missing effect", "gravity-direction", "gravity-direction", after=(0.5, 1.27))
    none = _round("no significant discrepancy")
    scored = [case_result(case, rounds, 1.3, {}, {}) for case, rounds in
              ((leaning, [gravity, none]), (leaning, [gravity, turned, none]), (leaning, [turned, none]),
               (upright, [gravity, turned, none]))]
    assert [r["correct"] for r in scored] == [True, True, False, False]
    assert false_naming(scored)["gravity-direction"] == [1, 1]  # only where the truth does not lean
    assert suite_scores(scored)["right_added_cases"] == 2


def test_wilson_intervals_bound_a_rate_honestly():
    """0 of 5 has an upper 95 % bound of 43 % (the issue's "0/5 bounds nothing"), 30 of 30 a
    lower one of 89 %; the interval holds the rate and stays in [0, 1]."""
    from BreastBiomechLib.discrepancy.suite.scores import wilson_interval

    assert wilson_interval(0, 5) == pytest.approx((0.0, 0.4345), abs=1e-4)
    assert wilson_interval(30, 30)[0] == pytest.approx(0.8865, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    for k, n in ((1, 2), (3, 40), (39, 40)):
        low, high = wilson_interval(k, n)
        assert 0.0 <= low <= k / n <= high <= 1.0


def test_the_runner_hands_the_fit_and_the_diagnosis_only_the_measured_copy():
    """No inverse crime: every call of the fit, the diagnosis and the fitted-case loader in the
    suite's runner takes the case folder ``measured`` (the copy of :func:`measured_copy`)."""
    import ast
    import inspect

    from BreastBiomechLib.discrepancy.suite import runner

    tree = ast.parse(inspect.getsource(runner))
    calls = [node for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
             and node.func.id in ("fit_compressed_case", "run_diagnosis", "load_fitted_case")]
    assert {c.func.id for c in calls} == {"fit_compressed_case", "run_diagnosis", "load_fitted_case"}
    for call in calls:
        case = call.args[0]
        text = ast.unparse(case)
        assert text in ("measured", "case_dir / 'measured'", "folder / 'measured'"), f"{call.func.id} reads {text}"
    def calls_in(function):
        body = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == function)
        return sorted((n.lineno, n.func.id, n) for n in ast.walk(body)
                      if isinstance(n, ast.Call) and isinstance(n.func, ast.Name))

    lines = {name: line for line, name, _ in calls_in("_fit_and_diagnose")}
    assert lines["fit_compressed_case"] < lines["run_diagnosis"]
    # each fit and diagnosis (one scan; with two, the second) of the measured copy, and the truth
    # read for scoring only after the diagnosis has answered
    order = [(name, ast.unparse(call.args[0])) for _, name, call in calls_in("_make_fit_and_diagnose")
             if name in ("_fit_and_diagnose", "scored_against_truth")]
    assert order == [("_fit_and_diagnose", "case"), ("scored_against_truth", "folder"), ("_fit_and_diagnose", "case"),
                     ("scored_against_truth", "folder")]
    fits = [call for _, name, call in calls_in("_make_fit_and_diagnose") if name == "_fit_and_diagnose"]
    assert [ast.unparse(call.args[1]) for call in fits] == ["measured", "measured"]
    # every fitting mesh, the prepared one and a varied case's own size, is made of the segmentation
    fitting = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
               and n.func.id == "_fitting_mesh"]
    assert len(fitting) == 2
    for call in fitting:
        labels = ast.unparse(call.args[0])
        assert "segmentation" in labels or labels == "result.labels", labels
        assert "phantom" not in labels and "case.labels" not in labels, labels


def test_a_case_another_run_is_making_is_waited_for_not_made_twice(tmp_path):
    """Suite runs side by side on one folder (shards of the cases): one that reaches a case the
    other is making waits for its lock and takes its result, instead of making it again into the
    same files."""
    import threading
    import time

    from BreastBiomechLib.discrepancy.suite import SuiteSettings, suite_cases
    from BreastBiomechLib.discrepancy.suite.runner import run_case, write_json

    case = suite_cases([1], ["null"])[0]
    folder = tmp_path / case.name
    folder.mkdir()
    (folder / "error.json").write_text("{}")  # an earlier attempt's failure
    # the other run (live: this process) is making it
    (folder / ".lock").write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))

    def the_other_run_finishes():
        time.sleep(2.5)
        write_json(folder / "result.json", {"case": case.name, "made_by": "the other run"})
        (folder / ".lock").unlink()

    other = threading.Thread(target=the_other_run_finishes)
    other.start()
    assert run_case(case, tmp_path, SuiteSettings())["made_by"] == "the other run"
    other.join()
    assert not (tmp_path / "anatomy1").exists() and not (folder / "truth").exists()


def test_a_lock_left_by_a_killed_run_is_taken_over(tmp_path):
    """A suite run killed while it made a case leaves the case's lock; the run started again on
    the folder sees that its process is gone and makes the case instead of waiting for it."""
    import subprocess
    import sys

    from BreastBiomechLib.discrepancy.suite.runner import _Lock

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    lock = tmp_path / ".lock"
    lock.write_text(json.dumps({"pid": gone.pid, "host": socket.gethostname()}))
    with _Lock(lock, wait_s=5.0):
        assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert not lock.exists()
    # a live holder is waited for, up to the wait
    lock.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
    with pytest.raises(TimeoutError, match="held for over 1 s by a live process"):
        with _Lock(lock, wait_s=1.0):
            pass


def test_the_suite_command_refuses_bad_arguments(tmp_path, capsys):
    from BreastBiomechLib.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["discrepancy-suite", "--out", str(tmp_path / "s"), "--landmark-noise-mm", "-1"])
    assert stop.value.code == 2 and "--landmark-noise-mm" in capsys.readouterr().err
    assert main(["discrepancy-suite", "--out", str(tmp_path / "none"), "--score-only"]) == 2
    assert "no suite run to score" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_only_the_suite_s_scoring_reads_a_hidden_effect_s_truth():
    """No inverse crime: the diagnosis, its effects and the fit never import the suite (which holds
    the hidden effects' true values) nor name a case's truth files; within the suite only the
    scoring and the runner's scoring step read the true values (``HiddenEffect.values``)."""
    import re
    from pathlib import Path

    library = Path(__file__).resolve().parents[3] / "BreastBiomechLib"
    guarded = [*(library / "discrepancy").glob("*.py"), *(library / "discrepancy" / "effects").glob("*.py"),
               *(library / "optimisation").glob("*.py")]
    assert len(guarded) > 20
    for path in guarded:
        text = path.read_text()
        code = re.sub(r'"""[\s\S]*?"""', "", text)  # docstrings may say what is never read
        assert "discrepancy.suite" not in code and "truth.json" not in code and "truth_mesh" not in code, path
        assert ".hidden.values" not in code, path
    readers = [p.name for p in (library / "discrepancy" / "suite").glob("*.py") if ".hidden.values" in p.read_text()]
    assert readers == ["scores.py"], readers
    # the truth's fields: read to make the truth (the runner's hidden_truth), to score (the
    # identifiability's sizes, the runner's record), never to choose a two-state case's second scan
    fields = sorted(p.name for p in (library / "discrepancy" / "suite").glob("*.py")
                    if re.search(r"hidden\.truth\b", re.sub(r'"""[\s\S]*?"""', "", p.read_text())))
    assert fields == ["identifiability.py", "runner.py"], fields
    # the second scan is the design's choice, made before the truth folder is touched
    import inspect

    from BreastBiomechLib.discrepancy.suite import runner

    second = inspect.getsource(runner._second_state).split('"""')[-1]
    assert second.index("designed_acquisition(record)") < second.index("truth_dir")
    assert "truth" not in inspect.getsource(runner._library_design).split('"""')[-1]
    # a phantom case's labels.nrrd is its ground truth: the diagnosis never names it, and in the fit
    # only the cohort study meshes it (on purpose, said in make_fitting_mesh) and the fit's refusal
    # to do so unasked names it in its message
    for path in guarded:
        code = re.sub(r'"""[\s\S]*?"""', "", path.read_text())
        if '"labels.nrrd"' in code or "'labels.nrrd'" in code:
            assert path.name in ("study.py", "case.py"), path
    case_code = (library / "optimisation" / "case.py").read_text()
    assert "read_label_map(labels)" in case_code and "labels or case" not in case_code


def _tested(name, absorbed=0.1, detectable=(0.2,), absorbed_by="glandular.E"):
    return {"name": name, "absorbed": absorbed, "detectable": list(detectable),
            "absorbed_by": {"name": absorbed_by, "correlation": 0.9}, "skipped": ""}


def test_the_identifiability_statements_are_scored_against_the_truth_s_size():
    def result(hidden, rounds):
        return case_result(SuiteCase(1, HIDDEN_EFFECTS[hidden]), rounds, 1.3, {}, {"fit": 10.0})

    # friction 0.6 hidden: seen from 0.2 on and named; seen only from 0.9 on and not named
    named = _round("missing effect", "friction", "friction", after=(0.8, 1.26), refit={"refined_values": [0.5]})
    named["diagnosis"]["candidates"] = [_tested("friction", detectable=(0.2,)) | {"refit": {}}]
    small = _round("no significant discrepancy")
    small["diagnosis"]["candidates"] = [_tested("friction", detectable=(0.9,))]
    beyond = _round("no significant discrepancy")  # detectable only past the range's end (1.5): not identifiable
    beyond["diagnosis"]["candidates"] = [_tested("friction", detectable=(2.1,))]
    seen = result("friction", [named, _round("no significant discrepancy")])
    missed = result("friction", [small])
    hopeless = result("friction", [beyond])
    assert seen["identifiability"]["friction"] == {"size": 0.6, "detectable": 0.2, "absorbed": 0.1,
                                                   "not_identifiable": False, "at_or_above_detectable": True,
                                                   "named": True}
    assert not missed["identifiability"]["friction"]["at_or_above_detectable"]
    assert not missed["identifiability"]["friction"]["not_identifiable"]
    assert hopeless["identifiability"]["friction"]["not_identifiable"]
    # the skin's size in the candidate's units: 100 kPa over 2 mm on 10 kPa fat is ln 10
    skin = _round("no significant discrepancy")
    skin["diagnosis"]["candidates"] = [_tested("skin", detectable=(3.0,))]
    thin = result("skin", [skin])["identifiability"]["skin"]
    assert thin["size"] == pytest.approx(np.log(10.0)) and not thin["at_or_above_detectable"]
    # a one-scan chest-wall case: right when the last round says the muscle takes the hold up
    hold = _round("no significant discrepancy")
    hold["diagnosis"]["candidates"] = [_tested("chest-wall", absorbed=0.85, detectable=(0.5,), absorbed_by="muscle.E")]
    other = _round("no significant discrepancy")
    other["diagnosis"]["candidates"] = [_tested("chest-wall", absorbed=0.85, absorbed_by="glandular.E")]
    seen_low = _round("no significant discrepancy")
    seen_low["diagnosis"]["candidates"] = [_tested("chest-wall", absorbed=0.3, detectable=(0.5,))]
    told, wrong_parameter, plainly_missed = (result("chest-wall", [r]) for r in (hold, other, seen_low))
    assert [told["correct"], wrong_parameter["correct"], plainly_missed["correct"]] == [True, False, False]
    # too small to see within its range (h 0 to 0.99): right where the verdict says the muscle takes most of it up
    for absorbed, detectable, right in ((0.78, 4.7, True), (0.43, 17.9, False), (0.78, 0.5, False)):
        small = _round("no significant discrepancy")
        small["diagnosis"]["candidates"] = [_tested("chest-wall", absorbed=absorbed, detectable=(detectable,),
                                                    absorbed_by="muscle.E")]
        assert result("chest-wall", [small])["correct"] is right
    # an unexplained discrepancy that says the muscle takes the hold up (it may be what is missing)
    # is right too; one that says nothing of it is not
    unexplained = _round("unexplained discrepancy")
    unexplained["diagnosis"]["candidates"] = hold["diagnosis"]["candidates"]
    silent = _round("unexplained discrepancy")
    silent["diagnosis"]["candidates"] = seen_low["diagnosis"]["candidates"]
    assert result("chest-wall", [unexplained])["correct"] and not result("chest-wall", [silent])["correct"]
    assert told["identifiability"]["chest-wall"]["not_identifiable"]
    assert told["identifiability"]["chest-wall"]["size"] == pytest.approx(3400.0 / 3740.0)
    assert plainly_missed["identifiability"]["chest-wall"]["at_or_above_detectable"]  # h 0.91 >= 0.5
    scores = suite_scores([seen, missed, hopeless, told, wrong_parameter, plainly_missed])
    calibration = scores["identifiability"]
    assert calibration["at_or_above_detectable"] == [1, 2]   # friction seen and named; the hold missed
    assert calibration["not_identifiable"] == [0, 3]        # friction past its range, the hold twice
    assert calibration["by_effect"]["friction"] == {"at_or_above_detectable": [1, 1], "not_identifiable": [0, 1]}
    text = scores_markdown(scores, [seen, missed])
    assert "| effects named, of those hidden at or above the smallest size the case said it could detect | 50% of 2" in text
    assert "| effects named, of those the case called not identifiable | 0% of 3" in text
    # a refinement is scored where it was first tested (after the effect it refines was added):
    # friction 0.9 and 0.3 is friction of geometric mean 0.52 and a log ratio ln 3 between the plates
    rough = _round("missing effect", "friction", "friction", after=(0.8, 1.26), refit={"refined_values": [0.5]})
    rough["diagnosis"]["candidates"] = [_tested("friction", detectable=(0.2,)) | {"refit": {}},
                                        _tested("friction-per-plate") | {"skipped": "comes first"}]
    apart = _round("no significant discrepancy")
    apart["diagnosis"]["candidates"] = [_tested("friction-per-plate", detectable=(13.4,))]
    per_plate = result("friction-per-plate", [rough, apart])
    assert per_plate["correct"] and per_plate["optional"] == ["friction-per-plate"]
    assert per_plate["identifiability"]["friction"]["size"] == pytest.approx(np.sqrt(0.27))
    row = per_plate["identifiability"]["friction-per-plate"]
    assert row["size"] == pytest.approx(np.log(3.0)) and row["detectable"] == 13.4 and row["not_identifiable"]
    # a leaning gravity's size is the angle between the truth's gravity and the one its case records
    from BreastBiomechLib.discrepancy.suite.identifiability import truth_sizes
    from BreastBiomechLib.discrepancy.suite.varied import varied_cases

    leaning = next(c for c in varied_cases(20) if c.hidden.name == "gravity").hidden
    g = np.array(leaning.truth["compression_gravity"])
    assert truth_sizes(leaning)["gravity-direction"] == pytest.approx(np.degrees(np.arccos(-g[2] / np.linalg.norm(g))))


def test_a_two_state_case_s_copy_holds_its_further_scan_and_the_first_scan_unchanged(two_state_case, tmp_path):
    from BreastBiomechLib.io.markups import read_markups

    one = measured_copy(two_state_case, tmp_path / "one", landmark_noise_mm=0.5, seed=3)
    both = measured_copy(two_state_case, tmp_path / "both", landmark_noise_mm=0.5, seed=3, states=True)
    held = {str(p.relative_to(both)) for p in both.rglob("*") if p.is_file()}
    assert not (one / "states").exists()
    assert held == {str(p.relative_to(one)) for p in one.rglob("*") if p.is_file()} | {
        "states/lateral/mr.nrrd", "states/lateral/landmarks.mrk.json", "states/lateral/plates.json"}
    assert not any("truth" in name or "force" in name for name in held)  # the force only where a case is told of it
    for name in ("landmarks.mrk.json", "compressed/landmarks.mrk.json"):  # the first scan's errors as without it
        np.testing.assert_array_equal(read_markups(one / name).positions, read_markups(both / name).positions)
    exact = read_markups(two_state_case / "states" / "lateral" / "landmarks.mrk.json").positions
    moved = read_markups(both / "states" / "lateral" / "landmarks.mrk.json").positions - exact
    assert 0.2 < moved.std() < 0.8


def test_a_design_s_acquisition_becomes_the_phantom_state_that_makes_it():
    from BreastBiomechLib.discrepancy.suite.two_state import designed_acquisition, state_spec
    from BreastBiomechLib.phantom.states import check_states

    planes = [{"name": "left"}, {"name": "right"}]
    further = state_spec({"name": "compression+10", "planes": planes}, 0.25)
    less = state_spec({"name": "compression-20", "planes": planes}, 0.4)
    assert (further.name, further.compression) == ("compression-up10", pytest.approx(0.35))
    assert (less.name, less.compression) == ("compression-down20", pytest.approx(0.2))
    check_states([further, less])  # names a case folder takes
    lateral = state_spec({"name": "only-right", "planes": planes}, 0.25)
    assert (lateral.name, lateral.moving_plate, lateral.compression) == ("only-right", "second", None)
    assert state_spec({"name": "only-left", "planes": planes}, 0.25).moving_plate == "first"
    half = state_spec({"name": "only-left-half", "planes": planes}, 0.25)  # the push a design halved
    assert (half.name, half.moving_plate, half.compression) == ("only-left-half", "first", pytest.approx(0.125))
    check_states([half])
    assert state_spec({"name": "rotated-SI", "planes": planes}, 0.25).axis == "SI"
    with pytest.raises(ValueError, match="no plate 'top'"):
        state_spec({"name": "only-top", "planes": planes}, 0.25)
    with pytest.raises(ValueError, match="not this one"):
        state_spec({"name": "posture-prone", "planes": planes}, 0.25)
    # the design's choice: the acquisition that tells most of the open candidates apart
    acquisitions = [{"name": n, "description": n, "planes": planes} for n in ("compression+10", "only-right")]

    def effect(name, now, seen):
        return {"effect": name, "title": name, "now_sigma": now, "detectable_sigma": 3.4,
                "acquisitions": [{"name": k, "separation_sigma": v} for k, v in seen.items()]}

    record = {"effects": [effect("chest-wall", 0.8, {"compression+10": 1.0, "only-right": 4.5}),
                          effect("skin", 0.5, {"compression+10": 3.6, "only-right": 3.5}),
                          effect("friction", 9.0, {"compression+10": 20.0, "only-right": 9.0})],  # told apart now
              "acquisitions": acquisitions, "failed": {}, "alpha": 0.01, "noise": {}}
    assert designed_acquisition(record)["name"] == "only-right"  # both open ones told apart; the compression one
    record["effects"][0]["acquisitions"][0]["separation_sigma"] = 3.0  # chest wall: 3.0 and 2.0, neither told
    record["effects"][0]["acquisitions"][1]["separation_sigma"] = 2.0
    assert designed_acquisition(record)["name"] == "compression+10"  # one each: the larger sum (6.6 against 5.5)
    with pytest.raises(RuntimeError, match="no acquisition"):
        designed_acquisition({**record, "acquisitions": [], "failed": {"only-right": "inverted"}})


def test_two_state_cases_are_named_by_their_second_scan_and_scored_against_their_first():
    hold = _round("no significant discrepancy")
    hold["diagnosis"]["candidates"] = [_tested("chest-wall", absorbed=0.85, absorbed_by="muscle.E")]
    named = _round("missing effect", "chest-wall", "chest-wall", after=(0.3, 1.27))
    one_scan = case_result(SuiteCase(1, HIDDEN_EFFECTS["chest-wall"]), [hold], 1.3, {}, {})
    still_absorbed = case_result(SuiteCase(1, HIDDEN_EFFECTS["chest-wall"], states=2), [hold], 1.3, {}, {})
    told = case_result(SuiteCase(1, HIDDEN_EFFECTS["chest-wall"], states=2), [named, _round("no significant discrepancy")],
                       1.3, {}, {})
    assert one_scan["correct"] and not still_absorbed["correct"] and told["correct"]  # two scans: only naming it
    assert SuiteCase(1, HIDDEN_EFFECTS["chest-wall"], states=2).name == "anatomy1-chest-wall-two-state"
    with pytest.raises(ValueError, match="one or two"):
        SuiteCase(1, HIDDEN_EFFECTS["null"], states=3)
    null = case_result(SuiteCase(2, HIDDEN_EFFECTS["null"], states=2), [_round("no significant discrepancy")], 1.3, {}, {})
    # the design predicted the first case's scan to tell the hold apart (4.1 sigma, 3.4 needed), not the second's
    results = [told | {"one_state": one_scan | {"correct": False},
                       "second_state": {"acquisition": "only-right", "predicted_sigma": {"chest-wall": 4.1},
                                        "needed_sigma": 3.4}},
               still_absorbed | {"one_state": one_scan,
                                 "second_state": {"acquisition": "only-right-half", "needed_sigma": 3.4,
                                                  "predicted_sigma": {"chest-wall": 2.0, "gravity": 5.0}}},
               null | {"one_state": null, "second_state": {"acquisition": "compression+10"}}]
    scores = suite_scores(results)
    assert scores["scans"] == {"one": [1, 2], "two": [1, 2], "null_one": [0, 1], "null_two": [0, 1],
                               "acquisitions": {"only-right": 1, "only-right-half": 1, "compression+10": 1},
                               "design_within_30": [0, 0], "predicted_told": [1, 2], "right_where_told": [1, 1]}
    text = scores_markdown(scores, results)
    assert "| the same cases with the designed second scan (compression+10 1, only-right 1, only-right-half 1) | 50% of 2" in text
    assert "predicted to tell the effect apart; right of those | 50% of 2" in text


def test_the_design_s_predicted_separations_are_set_against_those_the_two_scans_realised():
    from BreastBiomechLib.discrepancy.suite.two_state import realised_separations

    second = {"acquisition": "only-right", "predicted_sigma": {"chest-wall": 4.5, "skin": 2.0, "tumour": 1.0},
              "rivals": {"chest-wall": "heterogeneity", "skin": None, "tumour": "skin"}}
    first = _round("missing effect", "chest-wall")
    first["diagnosis"]["candidates"] = [
        {"name": "chest-wall", "separations": {"": 6.0, "heterogeneity": 4.0, "skin": 5.5}},
        {"name": "skin", "separations": {"": 1.0, "chest-wall": 0.9}},
        {"name": "tumour", "skipped": "no tumour"}]
    realised = realised_separations(first, second)
    assert realised == {"chest-wall": 4.0, "skin": 1.0, "tumour": None}  # against the design's own rival
    hold = _round("no significant discrepancy")
    result = case_result(SuiteCase(1, HIDDEN_EFFECTS["chest-wall"], states=2), [hold], 1.3, {}, {})
    scores = suite_scores([result | {"one_state": result, "second_state": second | {"realised_sigma": realised}}])
    assert scores["scans"]["design_within_30"] == [1, 2]  # 4.5 against 4.0 within; 2.0 against 1.0 not
