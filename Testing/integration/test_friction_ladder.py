"""Issue 77's ladder, its first rung: a hidden friction below sticking, fitted and diagnosed on the
truth mesh itself, so that nothing but the missing friction differs between the truth and the
model. The fit reads the truth mesh on purpose (a diagnostic rung, never a fit a user makes; it
finds a bias of the estimator, not of the mesh); the diagnosis reads the case without its truth
files. Above sticking no estimate can hold (docs/discrepancy.md, "Why friction refits below its
truth"): the rung hides mu 0.1, where the features still change with it."""

from __future__ import annotations

import json
import shutil

import pytest
from discrepancy_cases import FIT, without_truth

TRUTH_MU = 0.1


@pytest.mark.slow
def test_the_truth_mesh_rung_recovers_a_friction_below_sticking(tmp_path):
    from BreastBiomechLib.cli import main

    assert main(["phantom", "--seed", "2", "--volume-cm3", "400", "--spacing", "2", "2", "4", "--compressed",
                 "--compression", "0.4", "--truth-edge-mm", "8", "--device", "cpu", "--no-overview",
                 "--friction", str(TRUTH_MU), "--out", str(tmp_path / "made")]) == 0
    mesh = tmp_path / "truth_mesh.vtu"  # the rung's point: the truth's own mesh, copied out of its truth files
    shutil.copy2(tmp_path / "made" / "compressed" / "truth_mesh.vtu", mesh)
    case = without_truth(tmp_path / "made", tmp_path / "case")
    assert main(["optimise", str(case), "--out", str(tmp_path / "fit"), "--mesh", str(mesh), *FIT,
                 "--device", "cpu"]) == 0
    assert main(["diagnose", str(case), "--fit", str(tmp_path / "fit"), "--out", str(tmp_path / "dx"),
                 "--effects", "friction", "--rounds", "1", "--refine-iterations", "2", "--floor", "fixed",
                 "--interval", "profile", "--no-residual-field", "--device", "cpu", "--quiet"]) == 0
    record = json.loads((tmp_path / "dx" / "round-1.json").read_text())
    assert record["added"] == "friction", record["diagnosis"]["sentence"]
    refit = next(c for c in record["diagnosis"]["candidates"] if c["name"] == "friction")["refit"]
    [mu] = refit["refined_values"]
    [(low, high)] = refit["interval"]
    assert abs(mu - TRUTH_MU) <= 0.1, refit
    assert low <= TRUTH_MU <= high, refit
