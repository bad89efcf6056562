"""Prior-data conflict (issue 78 point 3): fitted moduli beyond their published range relative to
fat are flagged, and the candidates tested again with the modulus held at its range's end name
what the out-of-range modulus was taking up."""

from __future__ import annotations

import numpy as np
import pytest

from BreastBiomechLib.discrepancy import statistics
from BreastBiomechLib.discrepancy.priors import PLAUSIBLE_E, conflict_sentence, held_in_range, prior_conflicts
from BreastBiomechLib.optimisation.space import ParameterSpace


def _space():
    return ParameterSpace.for_model("iso-hetero", ["fat", "glandular", "muscle"], free=("E",))


def test_moduli_beyond_their_published_ratio_to_fat_are_flagged_with_the_nearest_end():
    space = _space()
    fat = space.materials(space.start())["fat"]["E"]
    inside = space.unit({"glandular.E": 2.0 * fat, "muscle.E": 8.0 * fat})
    assert prior_conflicts(space, inside) == []
    # muscle at 64x fat (above 20x), gland at 0.2x fat (below 0.5x)
    z = space.unit({"glandular.E": 0.2 * fat, "muscle.E": 64.0 * fat})
    found = {c["name"]: c for c in prior_conflicts(space, z)}
    assert set(found) == {"glandular.E", "muscle.E"}
    muscle = found["muscle.E"]
    assert muscle["ratio"] == pytest.approx(64.0)
    assert muscle["range"] == pytest.approx([PLAUSIBLE_E["muscle"].low * fat, PLAUSIBLE_E["muscle"].high * fat])
    assert muscle["bound"] == pytest.approx(20.0 * fat) and muscle["index"] == space.keys.index("muscle.E")
    # the bound's unit coordinate is the fit space's own: back in Pa it is the bound
    back = space.values(np.where(np.arange(len(z)) == muscle["index"], muscle["z_bound"], z))
    assert back["muscle.E"] == pytest.approx(20.0 * fat)
    assert found["glandular.E"]["bound"] == pytest.approx(0.5 * fat) and found["glandular.E"]["z_bound"] > z[0]
    # a homogeneous fit has no fat modulus besides its own reference: nothing to refer to
    homogeneous = ParameterSpace.for_model("iso-homo", ["fat", "glandular"], free=("E", "nu"))
    assert prior_conflicts(homogeneous, homogeneous.start()) == []


def test_a_candidate_taken_up_by_an_out_of_range_modulus_explains_the_residual_once_it_is_held():
    """Synthetic whitened sensitivities: the measured residual is a candidate's signature that the
    out-of-range modulus (column 0) reproduces almost entirely, as the chest-wall hold and the
    muscle modulus do. At the fit the candidate is not significant; with the modulus held at
    its range's end (its step back removes what it took up) the candidate explains the residual."""
    rng = np.random.default_rng(5)
    n = 300
    other = rng.standard_normal(n)
    signature = rng.standard_normal(n)
    modulus = signature + 0.01 * rng.standard_normal(n)  # the modulus reproduces the signature
    nuisance = np.column_stack([modulus, other])
    noise = rng.standard_normal(n)
    # the fit (least squares over the fitted parameters) moved the modulus out of its range to take
    # up the hidden effect's 4x signature; what is left is the data less that fit
    data = noise + 4.0 * signature
    moved, *_ = np.linalg.lstsq(nuisance, data, rcond=None)
    whitened = data - nuisance @ moved
    assert moved[0] == pytest.approx(4.0, abs=0.3)
    step_back = -moved[0]  # held at its range's end, here where it started
    channels = np.array(["landmarks"] * 60 + ["surface"] * 240)
    free = np.array([True, True])
    at_fit = statistics.score_by_channel(whitened, nuisance, signature[:, None], channels)
    assert at_fit["p_combined"] > 0.01
    # a candidate whose signature shares nothing with the hidden one's or the fitted parameters'
    unrelated = statistics.project_off(rng.standard_normal((n, 1)), statistics.basis(np.column_stack([signature,
                                                                                                      nuisance])))
    signatures = {"hidden": signature[:, None], "unrelated": unrelated}
    retest = held_in_range(whitened, nuisance, free, 0, step_back, signatures, channels, alpha=0.01,
                           before={"hidden": at_fit["p_combined"] * 2, "unrelated": 1.0})
    assert retest["explains"] == retest["significant"] == ["hidden"]
    assert retest["candidates"]["hidden"]["explained_fraction"] > 0.5
    assert retest["candidates"]["unrelated"]["p_adjusted"] > 0.01
    # holding a modulus that took nothing up (no step back) finds nothing either
    quiet = held_in_range(noise, nuisance, free, 0, 0.0, {"hidden": signature[:, None]}, channels, alpha=0.01,
                          before={"hidden": 1.0})
    assert quiet["explains"] == []
    # a candidate already significant at the fit is the verdict's to weigh, not an ambiguity of the conflict
    known = held_in_range(whitened, nuisance, free, 0, step_back, signatures, channels, alpha=0.01,
                          before={"hidden": 1e-6, "unrelated": 1.0})
    assert known["significant"] == ["hidden"] and known["explains"] == []
    # the residual of the model solved with the modulus held takes the linearised one's place
    assert not retest["solved"]
    same = held_in_range(whitened, nuisance, free, 0, step_back, signatures, channels, alpha=0.01,
                         before={"hidden": at_fit["p_combined"] * 2, "unrelated": 1.0},
                         solved=whitened - nuisance[:, 0] * step_back)
    assert same["solved"] and same["candidates"] == retest["candidates"]
    nothing_there = held_in_range(whitened, nuisance, free, 0, step_back, signatures, channels, alpha=0.01,
                                  before={"hidden": at_fit["p_combined"] * 2, "unrelated": 1.0}, solved=noise)
    assert nothing_there["explains"] == []  # solved, the modulus held did not bring the signature back


def test_the_sentence_says_the_conflict_and_the_ambiguity_only_where_the_retest_found_one():
    conflict = {"name": "muscle.E", "value": 640e3, "ratio": 64.0, "range": [5e3, 200e3], "bound": 200e3,
                "sources": "Gennisson et al. 2010"}
    titles = {"chest-wall": "chest-wall hold", "friction": "plate friction"}
    plain = conflict_sentence([conflict], None, titles)
    assert plain.startswith("Prior-data conflict: muscle E 640 kPa (64 x fat)") and "5-200 kPa" in plain
    assert "ambiguous" not in plain
    found = {**conflict, "retest": {"explains": ["chest-wall"],
                                    "candidates": {"chest-wall": {"explained_fraction": 0.62, "p_adjusted": 3e-5}}}}
    said = conflict_sentence([found], None, titles)
    assert "chest-wall hold would explain 62% of the residual" in said
    assert "ambiguous: chest-wall hold, or muscle E outside its plausible range" in said
    # the verdict already names it: no ambiguity to add
    named = conflict_sentence([found], "chest-wall", titles)
    assert "ambiguous" not in named and "no further candidate" in named
    assert conflict_sentence([], None, titles) == ""
