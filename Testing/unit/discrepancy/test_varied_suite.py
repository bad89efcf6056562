"""The varied suite (issue 77, point 6): each case draws what the fixed suite holds constant, the
draws are the same on every machine, and the scores are tabled per setting and per library effect."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.suite import SuiteSettings, scores_markdown, suite_scores
from BreastBiomechLib.discrepancy.suite.runner import case_settings
from BreastBiomechLib.discrepancy.suite.scores import by_setting, false_naming
from BreastBiomechLib.discrepancy.suite.varied import (EXTRA_ANATOMIES, FIT_BUDGETS, FIT_EDGES_MM, NULL_SHARE,
                                                       TRUTH_EDGES_MM, anatomy_parameters, setting_bin, sized_effect,
                                                       varied_cases)


def test_the_varied_cases_draw_every_setting_within_its_range_and_the_same_each_time():
    cases = varied_cases(90)
    assert [c.name for c in cases] == [c.name for c in varied_cases(90)]
    assert [c.draw for c in cases] == [c.draw for c in varied_cases(90)]
    assert [c.hidden.truth for c in cases] != [c.hidden.truth for c in varied_cases(90, seed=1)]
    assert len({c.name for c in cases}) == 90 and len({c.seed for c in cases}) == 90
    assert sum(c.hidden.name == "null" for c in cases) == 90 // NULL_SHARE  # 30 null cases
    assert {c.anatomy for c in cases} == set(range(1, 12))
    drawn = [c.drawn for c in cases]
    assert all(0.2 <= d["compression"] <= 0.5 and 0.2 <= d["landmark_noise_mm"] <= 1.0 for d in drawn)
    assert {d["moving_plate"] for d in drawn} == {"both", "second"}
    assert {d["fit_budget"] for d in drawn} == set(FIT_BUDGETS)
    assert {d["fit_edge_mm"] for d in drawn} == set(FIT_EDGES_MM)
    assert {d["truth_edge_mm"] for d in drawn} == set(TRUTH_EDGES_MM)
    assert all(d["fit_budget"] >= d["fit_population"] >= 4 for d in drawn)
    for case in cases:  # each drawn case makes valid settings
        settings = case_settings(case, SuiteSettings())
        assert settings.compression == case.drawn["compression"] and settings.fit_edge_mm == case.drawn["fit_edge_mm"]


def test_each_effect_is_sized_across_its_published_range():
    rng = np.random.default_rng(3)
    sizes = {name: [sized_effect(name, rng) for _ in range(200)]
             for name in ("friction", "plate-tilt", "skin", "gravity", "chest-wall", "stiff-band", "chest-wall-shift")}
    mu = [e.truth["friction"] for e in sizes["friction"]]
    assert 0.2 <= min(mu) < 0.3 and 0.9 < max(mu) <= 1.0
    assert all(e.values["friction"] == (e.truth["friction"],) for e in sizes["friction"])
    tilts = np.array([sum(e.truth["plate_tilt_deg"][0]) for e in sizes["plate-tilt"]])
    assert 0.5 <= np.abs(tilts).min() < 1.0 and 3.5 < np.abs(tilts).max() <= 4.0 and (tilts < 0).any()
    pivots = np.array([e.truth["plate_pivot_mm"][0] for e in sizes["plate-tilt"]])  # a paddle's mount, not its point
    assert np.abs(pivots[:, :2]).max() <= 60.0 and np.abs(pivots[:, :2]).max() > 50.0
    assert -20.0 <= pivots[:, 2].min() < -15.0 and pivots[:, 2].max() <= 0.0
    assert all(e.truth["plate_pivot_mm"][1] == [0.0, 0.0, 0.0] for e in sizes["plate-tilt"])
    skins = np.array([e.truth["skin"] for e in sizes["skin"]])
    assert skins[:, 0].min() >= 20e3 and skins[:, 0].max() <= 100e3 and 1.0 <= skins[:, 1].min() < 1.3
    for gravity in sizes["gravity"]:
        assert np.linalg.norm(gravity.truth["compression_gravity"]) == pytest.approx(9.81, abs=0.01)
    assert sized_effect("null", rng).truth == {} and sized_effect("stiff-band", rng).known is False
    per_plate = [sized_effect("friction-per-plate", rng) for _ in range(200)]
    pairs = np.array([e.truth["friction"] for e in per_plate])
    ratios = np.log(pairs[:, 0] / pairs[:, 1])
    assert np.log(2.0) - 0.01 <= np.abs(ratios).min() < 0.9 and 1.5 < np.abs(ratios).max() <= np.log(5.0) + 0.01
    assert (ratios < 0).any() and 0.2 <= np.sqrt(pairs.prod(axis=1)).min() < 0.3
    assert all(e.expected == ("friction",) and e.optional == ("friction-per-plate",) for e in per_plate)
    np.testing.assert_allclose([e.values["friction-per-plate"][0] for e in per_plate], ratios, atol=1e-4)
    assert not any(c.hidden.name == "friction-per-plate" for c in varied_cases(90))  # only where asked for
    assert {c.hidden.name for c in varied_cases(6, effects=["friction-per-plate"])} == {"null", "friction-per-plate"}
    both = sized_effect("friction+plate-tilt", rng)
    assert set(both.truth) == {"friction", "plate_tilt_deg", "plate_pivot_mm"} and both.expected == ("friction", "plate-tilt")


def test_anatomies_beyond_table_1_are_sweep_variants_and_unknown_ones_are_refused():
    from BreastBiomechLib.phantom.variants import sweep_variants

    family, index = EXTRA_ANATOMIES[7]
    assert anatomy_parameters(7) == sweep_variants(index + 1, family)[index]
    assert anatomy_parameters(1).volume_cm3 == 1364.0
    with pytest.raises(ValueError, match="anatomies are"):
        anatomy_parameters(12)
    with pytest.raises(ValueError, match="anatomies"):
        varied_cases(3, anatomies=(1, 14))
    with pytest.raises(ValueError, match="unknown hidden effects"):
        varied_cases(3, effects=["wind"])


def _result(name, kind, correct, draw, anatomy=1, added=(), expected=()):
    return {"case": name, "anatomy": anatomy, "hidden": name, "kind": kind, "expected": list(expected),
            "right_verdict": "", "answer": "none", "final": "none", "rounds": 1, "verdicts": ["v"],
            "added": list(added), "correct": correct, "false_unexplained_after_right": False, "estimates": {},
            "landmark_error_before_mm": 1.0, "nmi_before": 1.1, "nmi_truth": 1.2, "overall_statistic": 1.0,
            "overall_dof": 1, "overall_p": 0.5, "anatomy_figures": {}, "seconds": {"fit": 1.0}, "draw": draw}


def test_scores_are_tabled_per_setting_and_per_library_effect():
    """Right verdicts and false alarms per drawn setting's bin (with the anatomy's kind), and each
    library effect's false-naming rate: named in a case whose truth does not hide it."""
    results = [
        _result("a", "null", True, {"compression": 0.25, "fit_budget": 10}),
        _result("b", "null", False, {"compression": 0.45, "fit_budget": 200}, anatomy=7, added=["plate-tilt"]),
        _result("c", "single", True, {"compression": 0.45, "fit_budget": 60}, added=["friction"],
                expected=["friction"]),
        _result("d", "single", False, {"compression": 0.31, "fit_budget": 60}, anatomy=9, added=["plate-tilt"],
                expected=["skin"]),
        _result("e", "null", True, {}),  # a fixed suite's case: in no setting's table
    ]
    table = by_setting(results)
    assert table["compression"] == {"0.2-0.3": {"right": [0, 0], "false_alarms": [0, 1]},
                                    "0.3-0.4": {"right": [0, 1], "false_alarms": [0, 0]},
                                    "0.4+": {"right": [1, 1], "false_alarms": [1, 1]}}
    assert table["fit_budget"]["10-40"]["false_alarms"] == [0, 1] and table["fit_budget"]["100+"]["false_alarms"] == [1, 1]
    assert table["anatomy"]["beyond (6-11)"] == {"right": [0, 1], "false_alarms": [1, 1]}
    naming = false_naming(results)
    assert naming["plate-tilt"] == [2, 5] and naming["friction"] == [0, 4] and naming["skin"] == [0, 4]
    scores = suite_scores(results)
    text = scores_markdown(scores, results)
    assert "| compression | 0.4+ | 100% of 1 (95 % CI 21%-100%) | 100% of 1" in text
    assert "| plate-tilt | 40% of 5 (95 % CI" in text
    json.dumps(scores)  # the scores file holds them
    assert setting_bin("moving_plate", "second") == "second" and setting_bin("fit_edge_mm", 10.0) == "8+"
    assert setting_bin("landmark_noise_mm", 0.1) == "<0.2"


def test_a_case_at_another_element_size_gets_its_own_meshes_the_fitting_one_of_the_segmentation(compressed_case_dir,
                                                                                                  tmp_path):
    """A varied case's fitting mesh at its own size is made (once) from the anatomy's
    segmentation, never from the phantom's truth labels; its truth mesh from the truth labels;
    at the run's sizes the prepared meshes are used."""
    import shutil

    import SimpleITK as sitk

    from BreastBiomechLib.discrepancy.suite.runner import anatomy_mesh
    from BreastBiomechLib.io.meshes import read_vtu

    anatomy = tmp_path / "anatomy1"
    (anatomy / "phantom").mkdir(parents=True)
    for name in ("labels.nrrd", "landmarks.mrk.json"):
        shutil.copy2(compressed_case_dir / name, anatomy / "phantom" / name)
    truth_labels = sitk.ReadImage(str(compressed_case_dir / "labels.nrrd"))
    segmented = sitk.GetArrayFromImage(truth_labels)
    segmented[segmented == 2] = 1  # a segmentation that saw no gland: told apart from the truth by it
    (anatomy / "segmentation").mkdir()
    image = sitk.GetImageFromArray(segmented)
    image.CopyInformation(truth_labels)
    sitk.WriteImage(image, str(anatomy / "segmentation" / "labels.nrrd"))
    run = SuiteSettings()
    mine = case_settings(varied_cases(1)[0], run)
    assert anatomy_mesh(anatomy, "fitting", run, run) == anatomy / "fitting_mesh.vtu"
    fitting = anatomy_mesh(anatomy, "fitting", replace(mine, fit_edge_mm=12.0), run)
    truth = anatomy_mesh(anatomy, "truth", replace(mine, truth_edge_mm=12.0), run)
    assert fitting.name == "fitting_mesh-12mm.vtu" and truth.name == "truth_mesh-12mm.vtu"
    glandular = 2
    assert glandular not in set(read_vtu(fitting).cell_data["tissue"])
    assert glandular in set(read_vtu(truth).cell_data["tissue"])
    made = fitting.stat().st_mtime_ns
    anatomy_mesh(anatomy, "fitting", replace(mine, fit_edge_mm=12.0), run)
    assert fitting.stat().st_mtime_ns == made  # made once
