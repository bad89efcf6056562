"""Several measured states in one diagnosis, on conftest's small friction case (a copy without
its truth files, fitted on its first state): the case measured twice, its fit read as a joint fit
of both states. Two states that differ, with the chest-wall hold named only with the second:
docs/discrepancy.md (a GPU case)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest


def _measured_twice(case: Path, fit: Path, root: Path) -> tuple[Path, Path]:
    """``case`` with its compressed scan measured a second time (the same files as a further
    state "again") and ``fit`` as a joint fit of both (the same parameters, each state's
    solution the fit's): (case, fit) in ``root``."""
    from BreastBiomechLib.optimisation.case import case_record

    twice = Path(shutil.copytree(case, root / "case"))
    shutil.copytree(twice / "compressed", twice / "states" / "again")
    joint = Path(shutil.copytree(fit, root / "fit"))
    (joint / "case.json").write_text(json.dumps(case_record(twice, ["compressed", "again"])))
    (joint / "states" / "again").mkdir(parents=True)
    shutil.copy(joint / "deformed_mesh.vtu", joint / "states" / "again" / "deformed_mesh.vtu")
    return twice, joint


@pytest.mark.slow
def test_a_joint_fit_is_diagnosed_in_every_state_stacked(friction_case, tmp_path):
    """A joint fit's states are diagnosed together: every feature in every state, each variant
    solved in each state with that state's plates. With the same scan as both states, the two
    halves of every sensitivity agree, the first is the single scan's, every score statistic is
    twice the single scan's, and the round records each state's landmark error and NMI."""
    from BreastBiomechLib.discrepancy import DiagnosisSession, DiagnosisSettings, NoiseModel, observations_of
    from BreastBiomechLib.discrepancy import statistics
    from BreastBiomechLib.discrepancy.fitted import load_fitted_case
    from BreastBiomechLib.io.meshes import read_vtu

    case, fit = friction_case
    session = DiagnosisSession(*_measured_twice(case, fit, tmp_path), tmp_path / "diagnosis", effects=["skin"],
                               noise=NoiseModel(floor="fixed"), device="cpu", registration=None,
                               settings=DiagnosisSettings(refine_iterations=0, profile=False))
    assert session.fitted.state_names == ["compressed", "again"]
    single = observations_of(load_fitted_case(case, fit, device="cpu"),
                             read_vtu(fit / "deformed_mesh.vtu").point_data["displacement"], NoiseModel(floor="fixed"))
    n = len(single)
    stacked = session.observations
    assert len(stacked) == 2 * n and stacked.labels[n] == f"again: {single.labels[0]}"
    np.testing.assert_array_equal(stacked.measured, np.tile(single.measured, 2))
    record = session.diagnose()
    assert record["features"]["states"] == {"compressed": n, "again": n}
    sens = session.diagnosis.sensitivities
    np.testing.assert_allclose(sens.features[:n], single.predicted(session.fitted.first(sens.displacement)))
    for values in (sens.features, sens.nuisance, sens.effects["skin"]):
        np.testing.assert_allclose(values[n:], values[:n], atol=1e-9)
    # the stacked score test counts each feature twice
    weights = 1.0 / stacked.sigma
    whitened = weights * (stacked.measured - sens.features)
    free = (weights[:, None] * sens.nuisance)[:, [k not in session.diagnosis.held for k in sens.nuisance_keys]]
    half = statistics.score_by_channel(whitened[:n], free[:n], (weights[:, None] * sens.effects["skin"])[:n],
                                       stacked.channel[:n])
    [skin] = [c for c in record["diagnosis"]["candidates"] if c["name"] == "skin"]
    assert skin["statistic"] == pytest.approx(2 * half["statistic"], rel=1e-6)
    np.testing.assert_allclose(skin["estimate"], np.atleast_1d(half["estimate"]), rtol=1e-6)
    before = record["before"]
    assert before["states"]["again"]["nmi"] == pytest.approx(before["nmi"])
    assert before["states"]["again"]["landmark_error_mm"] == before["landmark_error_mm"]
    assert "in 2 measured states stacked (compressed " in (tmp_path / "diagnosis" / "report.md").read_text()
    # a state the fit fitted that the case no longer holds is named
    shutil.rmtree(tmp_path / "case" / "states" / "again")
    with pytest.raises(ValueError, match="no state 'again'"):
        DiagnosisSession(tmp_path / "case", tmp_path / "fit", tmp_path / "gone", device="cpu", registration=None)


@pytest.mark.slow
def test_the_chest_wall_hold_is_named_only_with_a_second_state(tmp_path, capsys):
    """Issue 78's point: one scan cannot tell a chest wall that holds the breast from a stiffer
    pectoral muscle, a second scan with the second plate alone pushing the breast along the
    chest can. The tests' 450 cm3 phantom with the hold hidden (a sliding chest wall with
    springs of 3.4 kPa/mm along it; 40 % LR by both plates, and a state "lateral" of 40 % by the
    second plate alone), fitted on an 8 mm mesh of its segmentation on the first state alone and
    on both jointly (12 solves each), each diagnosed for the hold (one round, the fixed floor):
    the single scan does not name it, the two scans do (5 min on 2 cores)."""
    from BreastBiomechLib.cli import main

    case = tmp_path / "case"
    assert main(["phantom", "--seed", "2", "--volume-cm3", "450", "--spacing", "1.5", "1.5", "3", "--compressed",
                 "--compression", "0.4", "--truth-edge-mm", "5", "--device", "cpu", "--no-overview",
                 "--chest-wall", "sliding", "--chest-wall-stiffness", "0", "3400",
                 "--state", "lateral", "moving-plate=second", "compression=0.4", "--out", str(case)]) == 0
    verdicts = {}
    for name, states in (("one", ["compressed"]), ("two", ["compressed", "lateral"])):
        fit, out = tmp_path / f"fit-{name}", tmp_path / f"diagnosis-{name}"
        assert main(["optimise", str(case), "--out", str(fit), "--model", "iso-hetero", "--free", "E",
                     "--optimiser", "cmaes-local", "--budget", "12", "--population", "4", "--edge-mm", "8",
                     "--states", *states, "--device", "cpu"]) == 0
        capsys.readouterr()
        assert main(["diagnose", str(case), "--fit", str(fit), "--out", str(out), "--effects", "chest-wall",
                     "--one-round", "--floor", "fixed", "--no-residual-field", "--device", "cpu", "--quiet",
                     "--json"]) == 0
        diagnosis = json.loads((out / "round-1.json").read_text())["diagnosis"]
        verdicts[name] = (diagnosis["verdict"], diagnosis.get("effect"))
    assert verdicts["one"][1] is None and verdicts["one"][0] != "missing effect"
    assert verdicts["two"] == ("missing effect", "chest-wall")
