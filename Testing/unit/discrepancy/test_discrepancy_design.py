"""The design of the next measurement's separations (discrepancy/design.py) on whitened rows made
by hand: an effect's separation is its signature beyond the fitted parameters and its rival,
stacking a state never lowers it, states are stacked parameter by parameter, and the closest
rival is the most nearly parallel candidate; the check of a separation by refitting
(discrepancy/design_check.py) on a model whose sensitivity fades as its parameter grows. The whole
design on a fitted case: Testing/integration/test_discrepancy.py."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy.design import Rows, residual_norm


def _rows(rng, n=40):
    stiffer = rng.standard_normal(n)  # a fitted parameter's signature
    hold = 0.9 * stiffer + 0.1 * rng.standard_normal(n)  # mostly taken up by it
    tilt = rng.standard_normal(n)
    twin = tilt + 0.05 * rng.standard_normal(n)  # nearly parallel to tilt
    return Rows({"muscle.E": stiffer}, {"chest-wall": hold, "plate-tilt": tilt, "plate-offset": twin}, n=n)


def test_a_separation_is_the_signature_beyond_the_fitted_parameters_and_the_rival():
    rng = np.random.default_rng(3)
    rows = _rows(rng)
    stiffer, hold = rows.nuisance["muscle.E"], rows.effects["chest-wall"]
    beyond = hold - stiffer * (stiffer @ hold) / (stiffer @ stiffer)
    assert rows.separation("chest-wall", None) == pytest.approx(np.linalg.norm(beyond))
    assert rows.separation("chest-wall", None) < 0.2 * np.linalg.norm(hold)  # absorbed
    # an effect in the span of the fitted parameters cannot be told apart; one the rival spans neither
    assert residual_norm(2.0 * stiffer, rows.fitted_span()) == pytest.approx(0.0, abs=1e-9)
    assert rows.separation("plate-offset", "plate-tilt") < 0.1 * rows.separation("plate-offset", None)
    assert rows.closest_rival("plate-offset") == "plate-tilt" and rows.closest_rival("plate-tilt") == "plate-offset"
    assert residual_norm(hold, np.zeros((len(hold), 0))) == pytest.approx(np.linalg.norm(hold))


def test_a_further_state_never_lowers_a_separation_and_is_stacked_parameter_by_parameter():
    rng = np.random.default_rng(4)
    now, further = _rows(rng), _rows(rng, n=25)
    further.nuisance = {"muscle.E": further.nuisance["muscle.E"], "glandular.E": rng.standard_normal(25)}
    del further.effects["plate-offset"]
    further.skipped = {"plate-offset": "not available"}
    stacked = now.stacked(further)
    assert stacked.n == 65 and list(stacked.nuisance) == ["muscle.E", "glandular.E"]
    np.testing.assert_array_equal(stacked.nuisance["glandular.E"][:40], 0.0)  # the first state lacks it
    assert set(stacked.effects) == {"chest-wall", "plate-tilt"} and stacked.skipped == {"plate-offset": "not available"}
    for effect, rival in (("chest-wall", "plate-tilt"), ("chest-wall", None), ("plate-tilt", "chest-wall")):
        assert stacked.separation(effect, rival) >= now.separation(effect, rival) - 1e-12
    # a state in which the hold moves the features against the stiffer muscle separates them
    further.effects["chest-wall"] = -0.9 * further.nuisance["muscle.E"]
    stacked = now.stacked(further)
    assert stacked.separation("chest-wall", None) > 3 * now.separation("chest-wall", None)


def test_each_acquisition_solves_only_the_effects_designed_for_and_their_closest_rivals():
    """A diagnosis designs for the few candidates it could not tell apart: every candidate is a
    rival in the measured states, but an acquisition need only solve those and their closest
    rivals (the plate tilt's six parameters are not solved again for the chest-wall hold)."""
    from BreastBiomechLib.discrepancy.design import acquisition_effects

    rng = np.random.default_rng(5)
    rows = _rows(rng)
    rows.effects["gravity"] = rows.effects["chest-wall"] + 0.2 * rng.standard_normal(rows.n)  # the hold's rival
    names = ["chest-wall", "plate-tilt", "plate-offset", "gravity", "skin"]  # skin: not tested (no rows)
    chosen, rivals, solved = acquisition_effects(rows, names, ["chest-wall"])
    assert chosen == ["chest-wall"] and rivals == {"chest-wall": "gravity"} and solved == ["chest-wall", "gravity"]
    chosen, rivals, solved = acquisition_effects(rows, names, ["plate-offset", "skin"])
    assert chosen == ["plate-offset", "skin"] and rivals == {"plate-offset": "plate-tilt"}
    assert solved == ["plate-tilt", "plate-offset", "skin"]
    chosen, rivals, solved = acquisition_effects(rows, names)  # designed for all: all solved
    assert chosen == solved == names and set(rivals) == {"chest-wall", "plate-tilt", "plate-offset", "gravity"}


def _candidate(name, absorbed, detectable, skipped=""):
    return {"name": name, "title": name, "absorbed": absorbed, "detectable": detectable, "skipped": skipped}


def test_the_next_measurement_is_designed_for_what_a_round_could_not_tell_apart():
    """A round's candidates the design is for: those the fitted parameters absorb (>= 80 %), those
    too small to see anywhere in their range, an ambiguous verdict's effects; not a candidate told
    apart, nor one skipped; with each one's closest rival beside it."""
    from BreastBiomechLib.discrepancy.design import undecided, with_rivals
    from BreastBiomechLib.discrepancy.effects.chest_wall import ChestWallHold
    from BreastBiomechLib.discrepancy.effects.friction import PlateFriction
    from BreastBiomechLib.discrepancy.effects.skin import SkinLayer
    from BreastBiomechLib.discrepancy.effects.tumour import TumourStiffness

    effects = {e.name: e for e in (ChestWallHold(), PlateFriction(), SkinLayer(), TumourStiffness())}
    diagnosis = {"verdict": "no significant discrepancy", "effect": None, "alternatives": [],
                 "candidates": [_candidate("chest-wall", 0.88, [0.5]), _candidate("friction", 0.1, [0.2]),
                                _candidate("skin", 0.2, [4.5]), _candidate("tumour", 0.95, [], skipped="no tumour")],
                 "correlations": {"chest-wall|friction": 0.3, "chest-wall|skin": 0.7, "friction|skin": 0.2}}
    assert undecided(diagnosis, effects) == ["chest-wall", "skin"]  # absorbed; 4.5 beyond the skin's 0-4
    assert with_rivals(diagnosis, ["chest-wall"]) == ["chest-wall", "skin"]
    told_apart = {**diagnosis, "candidates": [_candidate("friction", 0.1, [0.2])]}
    assert undecided(told_apart, effects) == []
    assert undecided({**told_apart, "verdict": "ambiguous", "alternatives": ["friction", "chest-wall"]},
                     effects) == ["friction", "chest-wall"]
    unseen = {**diagnosis, "candidates": [_candidate("friction", 0.3, [None])]}  # nothing would show it
    assert undecided(unseen, effects) == ["friction"]


def test_diagnose_prints_and_summarises_the_design_it_made(tmp_path, capsys):
    """`diagnose --design`'s words: the design.json of the diagnosis folder as sentences (one per
    candidate designed for) and under ``design`` in the --json summary; where nothing was designed,
    why: every candidate was told apart, or those that were not lie outside the effects chosen."""
    import json

    from BreastBiomechLib.cli.diagnose import _design_summary, _print_design
    from BreastBiomechLib.discrepancy.design import Design

    hold = {"effect": "chest-wall", "title": "chest-wall hold", "rival": "skin", "rival_title": "skin layer",
            "now_sigma": 0.8, "detectable_sigma": 3.4,
            "acquisitions": [{"name": "only-left", "description": "compress with only the left plate moving",
                              "separation_sigma": 4.5}]}
    record = {"round": 2, "designed_for": ["chest-wall"],
              **Design([hold], [{"name": "only-left", "skipped": {}}], {}, 0.01, {}).to_dict()}
    (tmp_path / "design.json").write_text(json.dumps(record))
    summary = _design_summary(tmp_path)
    assert summary["designed_for"] == ["chest-wall"]
    [sentence] = summary["sentences"]
    assert sentence.startswith("To tell chest-wall hold from skin layer") and "4.5 sigma (now 0.8" in sentence
    _print_design(tmp_path)
    assert capsys.readouterr().out == f"next measurement: {sentence}\n"
    (tmp_path / "design.json").write_text(json.dumps({**record, "designed_for": [], "effects": []}))
    _print_design(tmp_path)
    assert "every tested candidate could be told apart" in capsys.readouterr().out
    (tmp_path / "design.json").write_text(json.dumps({**record, "undecided": ["gravity"], "designed_for": [],
                                                      "effects": []}))
    assert _design_summary(tmp_path)["undecided"] == ["gravity"]
    _print_design(tmp_path)
    assert "(gravity) lie outside the effects chosen" in capsys.readouterr().out


def test_the_next_measurement_waits_for_the_rounds_to_be_decided(tmp_path):
    """A design is made once the rounds are decided: not with a round left for a person to decide
    (--one-round) nor with the decision itself (--add)."""
    from BreastBiomechLib.discrepancy import run_diagnosis

    for kwargs in ({"one_round": True}, {"add": "friction", "resume": True}):
        with pytest.raises(ValueError, match="once the rounds are decided"):
            run_diagnosis(tmp_path / "case", tmp_path / "fit", tmp_path / "out", design=(), **kwargs)


def _fading():
    """A one-parameter model whose sensitivity fades as the parameter grows (as a muscle's effect
    on the breast does as it stiffens): f(theta) = exp(-theta) a + exp(-2 theta) b, and its
    Jacobian."""
    a, b = np.array([1.0, 0.0, 0.5]), np.array([0.0, 1.0, 0.5])
    return (lambda th: np.exp(-th[0]) * a + np.exp(-2 * th[0]) * b,
            lambda th: (-np.exp(-th[0]) * a - 2 * np.exp(-2 * th[0]) * b)[:, None])


def test_a_refit_takes_up_what_the_linearisation_left_and_a_bound_stops_it():
    """Data made at another value of the parameter (an effect the model takes up wholly, but only
    nonlinearly): the linear separation at the start is 0.22 of the data's 1.40, the Broyden
    refit finds the value (1.2 within 0.01 in six steps) and leaves nothing beyond the span; with
    the parameter bounded before it (a modulus at the top of its range) it stops at the bound and
    half the linear separation stays; where the model does not solve it keeps the start."""
    from BreastBiomechLib.discrepancy.design_check import broyden_refit

    f, jacobian = _fading()
    start, low, high = np.array([0.0]), np.array([-5.0]), np.array([5.0])
    data = f(np.array([1.2]))
    residual = data - f(start)
    linear = residual_norm(residual, jacobian(start))
    assert linear == pytest.approx(0.222, abs=1e-3) and np.linalg.norm(residual) == pytest.approx(1.40, abs=0.01)
    made = broyden_refit(lambda th: data - f(th), residual, jacobian(start), start, low, high, iterations=6)
    assert made["theta"][0] == pytest.approx(1.2, abs=0.01) and made["steps"] == 6 and made["stopped"] is None
    assert made["rss"][0] == pytest.approx(residual @ residual) and made["rss"][-1] < 1e-6 * made["rss"][0]
    assert residual_norm(made["residual"], made["jacobian"]) < 0.01 * linear
    bounded = broyden_refit(lambda th: data - f(th), residual, jacobian(start), start, low, np.array([0.5]),
                            iterations=6)
    assert bounded["theta"][0] == 0.5 and bounded["stopped"] == "at the parameters' bounds"
    assert 0.4 * linear < residual_norm(bounded["residual"], bounded["jacobian"]) < linear
    failed = broyden_refit(lambda th: None, residual, jacobian(start), start, low, high)
    assert failed["steps"] == 0 and failed["theta"][0] == 0.0 and "did not solve" in failed["stopped"]
